"""Write small AMReX plotfiles for tests, in the layout AMReX's ``WriteMultiLevelPlotfile``
produces (``Header``, ``Level_N/Cell_H``, ``Level_N/Cell_D_00000``; see
:mod:`mi_amr.readers.amrex` for the format). Independent of the reader: every line is written
here from the layout, so a reader bug does not hide in a shared helper.

:func:`write_plotfile` with no arguments writes the tiny two-level plotfile the fuzz harness
(``tests/fuzz_inputs.py``) mutates.
"""

from pathlib import Path

import numpy as np

DESCRIPTORS = {
    "<f8": "((8, (64 11 52 0 1 12 0 1023)),(8, (8 7 6 5 4 3 2 1)))",
    "<f4": "((8, (32 8 23 0 1 9 0 127)),(4, (4 3 2 1)))",
}
# Level 0: one 8^3 box over [0, 1]^3; level 1 (ratio 2): two 4^3 boxes side by side in x.
LEVELS = (
    {"dx": 0.125, "domain": ((0, 0, 0), (7, 7, 7)), "boxes": [((0, 0, 0), (7, 7, 7))]},
    {"dx": 0.0625, "domain": ((0, 0, 0), (15, 15, 15)),
     "boxes": [((4, 4, 4), (7, 7, 7)), ((8, 4, 4), (11, 7, 7))]},
)
NAMES = ("density", "temp")


def field_value(name, x, y, z):
    """The test fields at world points: linear in position, different per field."""
    return 1.0 + x + 2.0 * y + 3.0 * z if name == "density" else 300.0 - 10.0 * x * y + z


def _box(lo, hi) -> str:
    return f"(({','.join(map(str, lo))}) ({','.join(map(str, hi))}) (0,0,0))"


def write_plotfile(root, levels=LEVELS, names=NAMES, dtype="<f8") -> Path:
    """Write the plotfile folder ``root``: ``levels`` as in :data:`LEVELS` (index boxes
    inclusive, ratio 2 between levels, ``prob_lo`` at the origin), cell-centred values of
    :func:`field_value`. Returns ``root``."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    dx = [lev["dx"] for lev in levels]
    hi = (np.array(levels[0]["domain"][1]) + 1) * dx[0]
    lines = ["HyperCLaw-V1.1", str(len(names)), *names, "3", "0.0", str(len(levels) - 1),
             "0 0 0", " ".join(f"{x:g}" for x in hi),
             " ".join("2" for _ in levels[1:]),
             " ".join(_box(*lev["domain"]) for lev in levels),
             " ".join("0" for _ in levels)]
    lines += [f"{h:g} {h:g} {h:g}" for h in dx]
    lines += ["0", "0"]
    for n, lev in enumerate(levels):
        lines += [f"{n} {len(lev['boxes'])} 0.0", "0"]
        for lo, bhi in lev["boxes"]:
            lines += [f"{lo[a] * dx[n]:g} {(bhi[a] + 1) * dx[n]:g}" for a in range(3)]
        lines.append(f"Level_{n}/Cell")
        _write_level(root / f"Level_{n}", lev, dx[n], names, dtype)
    (root / "Header").write_text("\n".join(lines) + "\n")
    return root


def _write_level(folder: Path, lev: dict, h: float, names, dtype: str) -> None:
    folder.mkdir(exist_ok=True)
    chunks, offsets, mins, maxs = [], [], [], []
    for lo, hi in lev["boxes"]:
        axes = [(np.arange(lo[a], hi[a] + 1) + 0.5) * h for a in range(3)]
        x, y, z = np.meshgrid(*axes, indexing="ij")
        data = np.stack([field_value(n, x, y, z) for n in names])
        offsets.append(sum(len(c) for c in chunks))
        head = f"FAB {DESCRIPTORS[dtype]}{_box(lo, hi)} {len(names)}\n".encode()
        # Fortran order (x fastest): the transpose of [c, i, j, k] written in C order.
        chunks.append(head + data.transpose(0, 3, 2, 1).astype(dtype).tobytes())
        mins.append(data.reshape(len(names), -1).min(axis=1))
        maxs.append(data.reshape(len(names), -1).max(axis=1))
    (folder / "Cell_D_00000").write_bytes(b"".join(chunks))
    boxes = lev["boxes"]
    text = ["1", "1", str(len(names)), "0", f"({len(boxes)} 0"]
    text += [_box(lo, hi) for lo, hi in boxes]
    text += [")", str(len(boxes))]
    text += [f"FabOnDisk: Cell_D_00000 {off}" for off in offsets]
    text.append("")
    for table in (mins, maxs):
        text.append(f"{len(boxes)},{len(names)}")
        text += ["".join(f"{v:.17g}," for v in row) for row in table]
    (folder / "Cell_H").write_text("\n".join(text) + "\n")
