"""Running the stability suite and reporting it: :data:`CASES` (every case by key),
:func:`run` (their rows), :func:`stability_table` (a Markdown table of the rows) and
:func:`main` (the command line). See :mod:`mi_amr.evaluation.stability`.
"""

from __future__ import annotations

import functools
import time

from mi_amr.evaluation.stability.cases_mitsuba import case_inside_ball, case_out_of_range, \
    case_temporal
from mi_amr.evaluation.stability.cases_rays import case_boundary_crossing, case_domain_faces, \
    case_grazing, case_inside, case_level_boundary, case_many_grids, case_nan, \
    case_nan_centre_lines, case_planes, case_spike_maximum, case_step_scale, case_tangent, \
    case_thin_sheet, case_thin_spike
from mi_amr.params import METHODS

CASES = {
    "thin_spike": case_thin_spike,
    "thin_sheet": case_thin_sheet,
    "grazing": case_grazing,
    "tangent": case_tangent,
    "spike_maximum": case_spike_maximum,
    "level_boundary": case_level_boundary,
    "boundary_crossing": case_boundary_crossing,
    "planes": case_planes,
    "lower_faces": functools.partial(case_domain_faces, 0.0),
    "upper_faces": functools.partial(case_domain_faces, 1.0),
    "inside": case_inside,
    "inside_ball": case_inside_ball,
    "out_of_range": case_out_of_range,
    "step_scale": case_step_scale,
    "nan": case_nan,
    "nan_centre_lines": case_nan_centre_lines,
    "many_grids": case_many_grids,
    "temporal": case_temporal,
}


def run(quick: bool = True, cases=None, progress: bool = False) -> list:
    """Measure every method on every case (or the named ones of :data:`CASES`); ``quick``
    uses fewer rays and smaller images (under a minute), the full version a few minutes.
    Returns the rows described in :mod:`mi_amr.evaluation.stability`; each row's
    ``metrics["case_seconds"]`` is its case's run time."""
    rows = []
    for name in (cases or CASES):
        t0 = time.perf_counter()
        out = CASES[name](quick)
        seconds = time.perf_counter() - t0
        for r in out:
            r["metrics"]["case_seconds"] = seconds
            r["metrics"]["case_key"] = name
        if progress:
            print(f"{name}: {seconds:.1f} s", flush=True)
        rows += out
    return rows


def _cell(r) -> str:
    """A row's cell of :func:`stability_table`."""
    if "headline" in r["metrics"]:
        return r["metrics"]["headline"]
    text = f"{r['missed']}/{r['expected']}"
    if r["expected"]:
        text += f" ({100 * r['missed'] / r['expected']:.0f}%)"
    if r["false"]:
        text += f", {r['false']} false"
    return text


def stability_table(rows) -> str:
    """Markdown: one row per case (and reconstruction), one column per method: missed / rays
    that must be hit (rate), and false hits when there are any; for the Mitsuba cases their
    headline numbers (non-finite pixels; hits, blank image and frame time relative to a
    normal frame; pixels that change with the jitter)."""
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    keys = []
    cells = {}
    for r in rows:
        key = r["case"] + (" (finest)" if r["reconstruction"] == "finest" else "")
        if key not in cells:
            keys.append(key)
            cells[key] = {}
        cells[key][r["method"]] = _cell(r)
    lines = ["| case | " + " | ".join(methods) + " |",
             "|---|" + "---|" * len(methods)]
    for key in keys:
        lines.append(f"| {key} | " + " | ".join(cells[key].get(m, "") for m in methods) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    """The command line (``python -m mi_amr.evaluation.stability``): the quick version, or
    ``--full``, of all cases or the ``--case`` ones; prints the table and every row's notes."""
    import argparse

    p = argparse.ArgumentParser(prog="python -m mi_amr.stability",
                                description="Measure every method on the failure cases.")
    p.add_argument("--full", action="store_true", help="the full version (a few minutes)")
    p.add_argument("--case", action="append", choices=list(CASES), help="only these cases")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    rows = run(quick=not args.full, cases=args.case, progress=True)
    print(stability_table(rows))
    print()
    for r in rows:
        print(f"{r['case']} / {r['method']} / {r['reconstruction']}: {r['notes']}")
    print(f"total {time.perf_counter() - t0:.1f} s")
    return 0

