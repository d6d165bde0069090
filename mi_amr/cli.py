"""Command line: ``python -m mi_amr {info,dataset,demo,...}``.

Every user mistake ends as one line ``error: ...`` on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mi_amr.errors import AMRError


def main(argv=None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "run"):
        parser.print_help()
        return 2
    try:
        return args.run(args) or 0
    except AMRError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m mi_amr",
                                description="Isosurfaces of AMR volumes with Mitsuba 3.")
    sub = p.add_subparsers(metavar="COMMAND")

    s = sub.add_parser("info", help="print the summary of an AMR file")
    s.add_argument("path")
    s.add_argument("--fields", nargs="+", help="read only these fields")
    s.set_defaults(run=_info)

    from mi_amr.synthetic.datasets import DATASETS, SIZES
    s = sub.add_parser("dataset", help="generate a synthetic dataset")
    s.add_argument("name", choices=sorted(DATASETS))
    s.add_argument("-o", "--output", required=True, help="output .npz file")
    s.add_argument("--size", choices=list(SIZES), default="default",
                   help="sphere_wake resolution (default: default)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--force", action="store_true", help="replace an existing file")
    s.set_defaults(run=_dataset)

    s = sub.add_parser("data", help="create every data file the scenes in scenes_xml/ need "
                                    "(skips files that exist)")
    s.set_defaults(run=_data)

    s = sub.add_parser("render", help="render a scene file")
    s.add_argument("scene", help="Mitsuba scene XML")
    s.add_argument("-o", "--output", required=True, help="image to write (.png or .exr)")
    s.add_argument("--spp", type=int, help="samples per pixel (the scene's 'spp' default)")
    s.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"),
                   help="image size (the scene's 'resx'/'resy' defaults)")
    s.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                   help="set a <default> of the scene, e.g. -D isovalue=0.1 (repeatable)")
    s.add_argument("--variant", default="llvm_ad_rgb",
                   help="Mitsuba variant (llvm_ad_rgb, cuda_ad_rgb, scalar_rgb)")
    s.add_argument("--force", action="store_true", help="replace an existing image")
    s.set_defaults(run=_render)

    s = sub.add_parser("bench", help="measure speed (and, in full, speed against accuracy)")
    s.add_argument("--frames", action="store_true",
                   help="only the frame timings of the default scene (first, warm, new "
                        "isovalue, new camera)")
    s.add_argument("--resolution", type=int, nargs=2, default=[1024, 1024], metavar=("W", "H"))
    s.add_argument("--variant", default="llvm_ad_rgb")
    s.add_argument("--quick", action="store_true",
                   help="a small sweep (two scenes, two step scales) for CI-sized checks")
    s.add_argument("--scene", action="append", help="sweep only these scenes (repeatable)")
    s.add_argument("--scaling", action="store_true",
                   help="only how the frame time grows with image size, grids and cells")
    s.add_argument("--peers", action="store_true",
                   help="only the peers (marching cubes + Mitsuba, yt) beside mi_amr exact")
    s.add_argument("--stability", action="store_true",
                   help="only the failure cases, every method on each (mi_amr.stability)")
    s.add_argument("--kdtree", action="store_true",
                   help="only validation and kd-tree build times for 10^4 and 10^5 grids")
    s.add_argument("--out", default="out/bench", help="folder for the results")
    s.set_defaults(run=_bench)

    s = sub.add_parser("reference", help="regenerate the exact reference images and hit "
                                         "buffers in reference/")
    s.add_argument("--regenerate", action="store_true", required=True,
                   help="required: this overwrites reference/")
    s.add_argument("--scene", action="append", help="only these scenes (repeatable)")
    s.set_defaults(run=_reference)

    s = sub.add_parser("demo", help="create the scenes' data, then render the default scene")
    s.add_argument("-o", "--output", default="out/sphere_wake.png")
    s.set_defaults(run=_demo)
    return p


def _info(args) -> None:
    from mi_amr.readers import load

    vol = load(args.path, fields=args.fields)
    print(vol.summary())


def _dataset(args) -> None:
    from mi_amr.synthetic.datasets import make

    t0 = time.perf_counter()
    written = make(args.name, args.output, size=args.size, seed=args.seed, overwrite=args.force)
    print(f"wrote {', '.join(str(p) for p in written)} in {time.perf_counter() - t0:.1f} s")


def _data(args) -> None:
    from mi_amr.workflows import project

    project.ensure_scene_data()


def _render(args) -> None:
    from mi_amr.workflows.render import render_file

    defines = {}
    for item in args.defines:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise AMRError(f"-D {item}: expected NAME=VALUE")
        defines[name] = value
    render_file(args.scene, args.output, spp=args.spp, resolution=args.resolution,
                defines=defines, variant=args.variant, overwrite=args.force)


def _bench(args) -> None:
    from mi_amr.evaluation.bench import run_frames, scaling, sweep
    from mi_amr.workflows import project

    project.ensure_scene_data()
    if args.frames:
        run_frames(args.out, resolution=tuple(args.resolution), variant=args.variant)
    elif args.scaling:
        scaling(args.out, variant=args.variant)
    elif args.kdtree:
        from mi_amr.evaluation.bench import kdtree_build

        kdtree_build(args.out)
    elif args.peers:
        from mi_amr.evaluation.bench import run_peers_only

        run_peers_only(args.out, variant=args.variant)
    elif args.stability:
        from mi_amr.evaluation.stability import run, stability_table

        table = stability_table(run(quick=args.quick, progress=True))
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "stability.md").write_text(table + "\n")
        print(table)
        print(f"wrote {out / 'stability.md'}")
    else:
        sweep(args.out, quick=args.quick, scenes=args.scene, variant=args.variant)


def _reference(args) -> None:
    from mi_amr.evaluation.references import SCENES, regenerate

    unknown = [n for n in (args.scene or []) if n not in SCENES]
    if unknown:
        raise AMRError(f"unknown reference scene(s) {unknown}; choose from {list(SCENES)}")
    regenerate(args.scene or SCENES)


def _demo(args) -> None:
    from mi_amr.workflows import project
    from mi_amr.workflows.render import render_file

    project.ensure_scene_data()
    render_file(project.scenes_dir() / "sphere_wake.xml", args.output, overwrite=True)
