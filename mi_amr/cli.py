"""Command line: ``python -m mi_amr {info,dataset,demo,...}``.

Every user mistake ends as one line ``error: ...`` on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

from mi_amr.errors import AMRError


def main(argv=None, prog: str = "mi-amr") -> int:
    """Run the command line; ``prog`` is the name usage lines show (the installed ``mi-amr``
    script, or ``python -m mi_amr`` from ``__main__``)."""
    parser = _parser(prog)
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


def _parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog,
                                description="Isosurfaces of AMR volumes with Mitsuba 3.")
    sub = p.add_subparsers(metavar="COMMAND")

    _add_data_commands(sub)
    _add_render(sub)
    _add_bench(sub)
    _add_view(sub)
    return p


def _add_data_commands(sub) -> None:
    """``info``, ``dataset``, ``data``."""
    s = sub.add_parser("info", help="print the summary of an AMR file, each field's range, "
                                    "percentiles and suggested isovalues")
    s.add_argument("path")
    s.add_argument("--fields", nargs="+", help="only these fields (stored, or derived: "
                                               "q_criterion, speed, vorticity)")
    _add_allow_nonfinite(s)
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


def _add_render(sub) -> None:
    """``render``, ``movie``, ``histogram``."""
    s = sub.add_parser("render", help="render a scene file or a data file")
    s.add_argument("scene", help="Mitsuba scene XML, or a data file (a scene is made for it)")
    s.add_argument("-o", "--output", required=True, help="image to write (.png or .exr)")
    s.add_argument("--spp", type=int, help="samples per pixel (the scene's 'spp' default)")
    s.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"),
                   help="image size (the scene's 'resx'/'resy' defaults)")
    s.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                   help="set a <default> of the scene, e.g. -D isovalue=0.1 (repeatable)")
    s.add_argument("--variant", default="llvm_ad_rgb",
                   help="Mitsuba variant (llvm_ad_rgb, cuda_ad_rgb, scalar_rgb)")
    s.add_argument("--force", action="store_true", help="replace an existing image")
    s.add_argument("--aovs", action="store_true",
                   help="also write the isosurface's depth, normal, position, values, level and "
                        "grid as channels of the (.exr) image")
    _add_data_scene(s)
    s.set_defaults(run=_render)
    _add_movie(sub)

    s = sub.add_parser("histogram", help="the 2D histogram of a field's value against its "
                                         "gradient magnitude (for a 2D transfer function)")
    s.add_argument("path", help="an AMR file")
    s.add_argument("--field", required=True, help="stored or derived field")
    s.add_argument("-o", "--output", required=True, help="PNG to write")
    s.add_argument("--bins", type=int, default=256)
    _add_allow_nonfinite(s)
    axis = s.add_mutually_exclusive_group()
    axis.add_argument("--log-value", dest="value_scale", action="store_const", const="log",
                      default="auto", help="a log value axis (symlog where values reach 0); "
                                           "default: log when the values span 3+ decades")
    axis.add_argument("--linear-value", dest="value_scale", action="store_const",
                      const="linear", help="a linear value axis")
    s.add_argument("--force", action="store_true", help="replace an existing image")
    s.set_defaults(run=_histogram)


def _add_bench(sub) -> None:
    """``bench``, ``reference``, ``demo``."""
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
                   help="only the peers (marching cubes + Mitsuba, yt, VTK's AMR contour + "
                        "Mitsuba) beside mi_amr exact")
    s.add_argument("--stability", action="store_true",
                   help="only the failure cases, every method on each (mi_amr.stability)")
    s.add_argument("--kdtree", action="store_true",
                   help="only validation and kd-tree build times for 10^4 and 10^5 grids")
    s.add_argument("--limit", action="store_true",
                   help="only the frame against a mesh of the same surface (4 sizes) and the "
                        "load against a raw read of the file, writes limit.md")
    s.add_argument("--volume", action="store_true",
                   help="only volume mode: its frames beside surface mode's and yt's "
                        "(volume_speed.md), then each method and step against exact at 64 spp "
                        "(volume.md, volume_chart.png); --quick: 32^2, a smoke test")
    s.add_argument("--speed", action="store_true",
                   help="with --volume: only the frames beside surface mode's and yt's at "
                        "256^2 and 1024^2, writes volume_speed.md")
    s.add_argument("--shadows", action="store_true",
                   help="with --volume: only the volume shadows (off, cache, exact) on the "
                        "one- and three-band scenes beside surface mode, writes shadows.md")
    s.add_argument("--movie", action="store_true",
                   help="only the movie frame rates (1 and 2 workers) and one time step's "
                        "cost, writes movie.md")
    s.add_argument("--soak", action="store_true",
                   help="only the soak runs (not in make test): 2,000 random viewer changes "
                        "(memory growth, kernels compiled, files left behind), writes soak.md")
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


def _info(args) -> None:
    from mi_amr.workflows.info import info_text

    print(info_text(args.path, args.fields, allow_nonfinite=args.allow_nonfinite))


def _dataset(args) -> None:
    from mi_amr.synthetic.datasets import make

    t0 = time.perf_counter()
    written = make(args.name, args.output, size=args.size, seed=args.seed, overwrite=args.force)
    print(f"wrote {', '.join(str(p) for p in written)} in {time.perf_counter() - t0:.1f} s")


def _data(args) -> None:
    from mi_amr.workflows import project

    project.ensure_scene_data()


def _add_data_scene(s) -> None:
    """The options of a data file given where a scene goes."""
    s.add_argument("--field", help="data file: the field to show, stored or derived "
                                   "(q_criterion, speed, vorticity); default: the first stored")
    s.add_argument("--isovalue", type=float,
                   help="data file: the isovalue (default: picked from the histogram)")
    s.add_argument("--mode", choices=("surface", "volume"),
                   help="data file: the isosurface (surface, the default) or a translucent "
                        "band about the isovalue (volume; its width picked from the histogram)")
    s.add_argument("--save-scene", metavar="XML", help="data file: also write the scene made "
                                                      "for it here (for editing)")
    _add_allow_nonfinite(s, "data file: ")


def _add_allow_nonfinite(s, where: str = "") -> None:
    s.add_argument("--allow-nonfinite", action="store_true",
                   help=f"{where}keep NaN and Inf values as missing data (else a file holding "
                        f"them is refused)")


def _data_scene(args, source, resolution=None, series: bool = False, offer=None):
    """The scene file for ``source`` (a block: a data file's is made, and removed after);
    ``series``: the first of a time series' data files; ``offer``: as
    :func:`~mi_amr.workflows.datafile.scene_file` takes it."""
    from mi_amr.workflows.datafile import (asked_params, check_data_defines, is_scene_file,
                                           scene_file)
    from mi_amr.workflows.movie.spec import parse_sweep

    isovalue, listed = args.isovalue, None
    if not is_scene_file(source):
        defines = _defines(getattr(args, "defines", []))
        check_data_defines(defines)
        if "isovalue" in defines:
            listed = _defined_isovalue(defines["isovalue"], isovalue)
            isovalue = listed[0]
    sweep = getattr(args, "isovalues", None)
    framed = "data" if series else parse_sweep(sweep)[:2] if sweep is not None else \
        (min(listed), max(listed)) if listed and len(listed) > 1 else None
    return scene_file(source, field=args.field, isovalue=isovalue, resolution=resolution,
                      spp=getattr(args, "spp", None), save_scene=args.save_scene,
                      force=getattr(args, "force", False), framed_values=framed,
                      offer=offer, **asked_params(args.allow_nonfinite, args.mode))


def _defined_isovalue(text: str, given) -> list:
    """The isovalues that ``-D isovalue=text`` sets for a data file's scene (a number or a
    list): its scene is made for the first (no other is picked) and its camera frames them
    all. ``given``: ``--isovalue``'s, which may not be given as well."""
    if given is not None:
        raise AMRError("--isovalue and -D isovalue both set the isovalue of a data file's "
                       "scene; give one")
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        values = []
    if not values:
        raise AMRError(f"-D isovalue: expected a number or a comma-separated list of numbers, "
                       f"got {text!r}")
    return values


def _preparations(variant: str):
    """The volumes that amr_iso prepares on ``variant`` (set here), to which a data file's
    scene offers the field its isovalue pick read: the scene's load does not read it again."""
    from mi_amr.plugin.integrator import register
    from mi_amr.plugin.scene import use_variant

    use_variant(variant)
    return register()


def _render(args) -> None:
    from mi_amr.workflows.render import check_image_request, render_file

    # (Before a data file's scene is made: its isovalue pick reads the whole file.)
    check_image_request(Path(args.output), args.spp, args.resolution, args.force, args.aovs)
    started = time.perf_counter()       # (the total counts a data file's scene being made)
    offer = _preparations(args.variant).offer
    with _data_scene(args, args.scene, args.resolution, offer=offer) as scene:
        render_file(scene, args.output, spp=args.spp, resolution=args.resolution,
                    defines=_defines(args.defines), variant=args.variant,
                    overwrite=args.force, aovs=args.aovs, started=started)


def _histogram(args) -> None:
    from mi_amr.workflows.histogram import histogram_figure

    if args.bins < 2:
        raise AMRError(f"--bins must be >= 2, got {args.bins}")
    out = histogram_figure(args.path, args.field, args.output, bins=args.bins,
                           overwrite=args.force, value_scale=args.value_scale,
                           allow_nonfinite=args.allow_nonfinite)
    print(f"wrote {out}")


def _defines(items) -> dict:
    defines = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise AMRError(f"-D {item}: expected NAME=VALUE")
        defines[name] = value
    return defines


def _add_movie(sub) -> None:
    s = sub.add_parser("movie", help="render a movie: an orbit, an isovalue sweep, keyframes or "
                                     "a time series of files, in parallel on Dask")
    s.add_argument("scene", nargs="+", metavar="SCENE|FILE",
                   help="Mitsuba scene XML, or the data files of a time series (globs too; a "
                        "scene is made for the first)")
    s.add_argument("-o", "--output", required=True, help="folder for frame_00000.png ...")
    s.add_argument("--files", help="the time series: a glob or a comma-separated list (natural "
                                   "order); replaces the scene's data file frame by frame")
    s.add_argument("--orbit", type=float, metavar="DEGREES",
                   help="turn the camera about its target on its up axis over the movie")
    s.add_argument("--frames", type=int, help="number of frames (default: one per file, or "
                                              "the keyframes', or 60)")
    s.add_argument("--isovalues", metavar="START:STOP",
                   help="sweep the first isovalue (prefix log: for a logarithmic sweep)")
    s.add_argument("--keyframes", help="a TOML or JSON keyframe file (camera, isovalue, "
                                       "colour range by frame number)")
    s.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"))
    s.add_argument("--spp", type=int)
    s.add_argument("--color-range", nargs="+", metavar="LO HI | series",
                   help="the colour range: two numbers, or 'series' (one range over every "
                        "file's colour field; the default for a time series)")
    s.add_argument("--workers", type=int, default=1,
                   help="Dask worker processes on this machine (1: render in this process)")
    s.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask cluster, e.g. tcp://host:8786 (instead of --workers)")
    s.add_argument("--mp4", help="also encode the frames as this MP4")
    s.add_argument("--fps", type=int, default=24)
    s.add_argument("--format", choices=("png", "exr"), default="png")
    s.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                   help="set a <default> of the scene (repeatable)")
    s.add_argument("--variant", default="llvm_ad_rgb")
    s.add_argument("--force", action="store_true", help="render (and encode) again what exists")
    _add_data_scene(s)
    s.set_defaults(run=_movie)


def _color_range(values):
    if values is None:
        return None
    if values == ["series"]:
        return "series"
    try:
        lo, hi = (float(v) for v in values)
    except ValueError:
        raise AMRError(f"--color-range: expected LO HI or 'series', got {' '.join(values)}") \
            from None
    if not lo < hi:
        raise AMRError(f"--color-range: needs LO < HI, got {lo:g} {hi:g}")
    return (lo, hi)


def _movie(args) -> int:
    from mi_amr.workflows.datafile import movie_inputs

    if args.workers < 1:
        raise AMRError(f"--workers must be >= 1, got {args.workers}")
    source, files = movie_inputs(args.scene, args.files)
    # Frames rendered in this process take the field the isovalue pick read; Dask workers
    # (other processes) could not, and the volume would be held through the movie.
    here = args.workers == 1 and args.scheduler is None
    offer = _preparations(args.variant).offer if here else None
    # (A time series' later steps may hold their surfaces elsewhere: its data's bounds.)
    with _data_scene(args, source, args.resolution, series=len(files or ()) > 1,
                     offer=offer) as scene:
        summary = _run_movie(scene, files, args)
    print(summary.text())
    if args.mp4 and not summary.failed:
        print(f"wrote {args.mp4}")
    return 1 if summary.failed else 0


def _run_movie(scene, files, args):
    from mi_amr.workflows.movie import render_movie

    return render_movie(scene, args.output, frames=args.frames, files=files,
                        orbit=args.orbit, isovalues=args.isovalues, keyframes=args.keyframes,
                        color_range=_color_range(args.color_range),
                        resolution=args.resolution, spp=args.spp, fmt=args.format,
                        workers=args.workers, scheduler=args.scheduler, mp4=args.mp4,
                        fps=args.fps, force=args.force, defines=_defines(args.defines),
                        variant=args.variant)


def _bench(args) -> None:
    from mi_amr.evaluation.bench import run_frames, scaling, sweep
    from mi_amr.workflows import project

    if (args.shadows or args.speed) and not args.volume:
        raise AMRError("bench: --shadows and --speed choose a part of --volume; add --volume")
    if args.shadows and args.speed:
        raise AMRError("bench: --shadows and --speed are two parts of --volume; pick one")
    _bench_folder(Path(args.out))
    project.ensure_scene_data()
    # Loads are timed as first loads: no snapshot read or written, here or in the processes
    # a benchmark starts (bench --limit times the read back in a folder of its own).
    os.environ["MI_AMR_CACHE"] = "off"
    if args.limit:
        from mi_amr.evaluation.limit_bench import run_limit_bench

        run_limit_bench(args.out, variant=args.variant)
    elif args.volume and args.shadows:
        from mi_amr.evaluation.shadow_bench import shadow_sweep

        quick = {"res": 64, "frames": 1, "accuracy": (32, 2, 4)} if args.quick else {}
        shadow_sweep(args.out, variant=args.variant, **quick)
    elif args.volume:
        from mi_amr.evaluation.volume_bench import volume_sweep
        from mi_amr.evaluation.volume_speed_bench import volume_speed

        volume_speed(args.out, quick=args.quick, variant=args.variant)
        if not args.speed:
            volume_sweep(args.out, quick=args.quick, variant=args.variant)
    elif args.movie:
        from mi_amr.evaluation.movie_bench import run_movie_bench

        run_movie_bench(args.out)
    elif args.soak:
        from mi_amr.evaluation.soak import run_soak

        run_soak(args.out)
    elif args.viewer:
        from mi_amr.evaluation.bench import run_viewer

        run_viewer(args.out, scene=_viewer_scene(args.scene), variant=args.variant)
    elif args.frames:
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


def _bench_folder(out: Path) -> None:
    """Make the benchmark's results folder before any work, or say why it cannot be."""
    if out.exists() and not out.is_dir():
        raise AMRError(f"bench: --out {out} is a file, not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise AMRError(f"bench: cannot make the results folder --out {out}: {e.strerror}")


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


def _viewer_scene(names):
    """``bench --viewer --scene NAME``: the one scene of ``scenes_xml/`` (a file name, with or
    without ``.xml``) or scene file to time; None: the default scene."""
    from mi_amr.workflows import project

    if not names:
        return None
    if len(names) > 1:
        raise AMRError(f"bench --viewer: give one --scene, got {len(names)}")
    name = names[0]
    for path in (Path(name), project.scenes_dir() / name, project.scenes_dir() / f"{name}.xml"):
        if path.is_file():
            return path
    raise AMRError(f"bench --viewer: scene {name!r} is neither a file nor a scene of "
                   f"{project.scenes_dir()}")


def _add_view(sub) -> None:
    """``view``, and ``bench --viewer`` (kept here so the viewer's options sit together)."""
    sub.choices["bench"].add_argument(
        "--viewer", action="store_true",
        help="only the viewer's slider-to-image round trip in a browser (512^2; the "
             "default scene, or --scene NAME of scenes_xml/ or a scene file)")
    s = sub.add_parser("view", help="explore a scene in the browser: isovalues, method, "
                                    "colours, camera, light; save images, scenes, keyframes")
    s.add_argument("scene", help="Mitsuba scene XML rendered by amr_iso, or a data file")
    s.add_argument("--port", type=int, default=8080, help="port (default 8080; 0: a free one)")
    s.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only)")
    s.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                   help="also answer requests that name this host (a DNS name or address "
                        "other machines use to reach this one; repeatable). The loopback "
                        "names and the --host address are always allowed; with --host "
                        "0.0.0.0 so are this machine's own names and addresses")
    s.add_argument("--no-browser", action="store_true", help="do not open a browser")
    s.add_argument("--out", default="out",
                   help="folder the page saves images, scenes and keyframes in (default ./out)")
    s.add_argument("--files", nargs="+", default=[], metavar="FILE",
                   help="a time series: data files (globs, quoted: 'run/plt*') shown as the "
                        "scene's time steps, with a time slider; the page may also open "
                        "these files")
    s.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"),
                   help="size of the view (default: 512 wide, the scene's aspect)")
    s.add_argument("--spp", type=int, default=4,
                   help="samples per pixel of the refined image (default 4)")
    s.add_argument("--preview-scale", type=int, default=2,
                   help="while a control moves, 1 spp at 1/N of the size (default 2)")
    s.add_argument("--preview-budget", type=float, default=None, metavar="SECONDS",
                   help="a preview slower than this makes the next ones half the side, down "
                        "to 1/8 (one faster than a sixth of it, twice the side again; "
                        "default 0.25; 0: the previews keep --preview-scale)")
    s.add_argument("--variant", default="llvm_ad_rgb")
    _add_data_scene(s)
    s.set_defaults(run=_view)


def _view(args) -> None:
    from mi_amr.workflows.viewer import serve
    from mi_amr.workflows.viewer.server import MAX_PORT

    if args.spp < 1 or args.preview_scale < 1 or (args.resolution and min(args.resolution) < 1):
        raise AMRError("view: --spp, --preview-scale and --resolution must be positive")
    budget = args.preview_budget
    if budget is not None and not (math.isfinite(budget) and budget >= 0):
        raise AMRError(f"view: --preview-budget must be 0 or more seconds, got {budget:g}")
    if not 0 <= args.port <= MAX_PORT:
        raise AMRError(f"view: --port must be 0 (a free one) to {MAX_PORT}, got {args.port}")
    with _data_scene(args, args.scene, series=bool(args.files),
                     offer=_preparations(args.variant).offer) as scene:
        serve(scene, host=args.host, port=args.port, open_browser=not args.no_browser,
              out_dir=args.out, files=args.files, resolution=args.resolution, spp=args.spp,
              preview_scale=args.preview_scale, variant=args.variant,
              allow_hosts=args.allow_host, preview_budget_s=budget)
