"""``render``, ``view`` and ``movie`` given a data file instead of a scene: the scene made for it
(:mod:`mi_amr.plugin.autoscene`) written as a Mitsuba XML file that the usual scene workflows
then take, either where ``--save-scene`` says or in a temporary folder that is removed after.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
from pathlib import Path

from mi_amr.core.atomic import check_output, replacing
from mi_amr.errors import AMRError, did_you_mean

SCENE_SUFFIX = ".xml"


def is_scene_file(path) -> bool:
    """Whether ``path`` names a Mitsuba scene (``.xml``) rather than a data file."""
    return Path(path).suffix.lower() == SCENE_SUFFIX


def check_data_defines(defines) -> None:
    """One error for a ``-D`` name (of ``defines``) that a data file's scene has no
    ``<default>`` for, before the scene is made (its other parameters are the XML's own)."""
    from mi_amr.plugin.autoscene import XML_DEFAULTS

    for name in defines:
        if name not in XML_DEFAULTS:
            raise AMRError(f"-D {name}: a data file's scene takes -D for "
                           f"{', '.join(XML_DEFAULTS)}{did_you_mean(name, XML_DEFAULTS)}; "
                           f"to set its other amr_iso "
                           f"parameters, write it with --save-scene scene.xml, edit that and "
                           f"render it")


def asked_params(allow_nonfinite: bool = False, mode=None) -> dict:
    """The amr_iso parameters of a data file's scene that the user asked for, for
    :func:`scene_file`: only those, so that a scene made without them does not name them (and
    a scene file given instead can be told which ones apply to data files only)."""
    params = {"allow_nonfinite": True} if allow_nonfinite else {}
    if mode is not None:
        params["mode"] = mode
    return params


@contextlib.contextmanager
def scene_file(source, *, field=None, isovalue=None, resolution=None, spp=None,
               save_scene=None, force: bool = False, say=print, framed_values=None,
               sets_isovalue: str = "--isovalue", offer=None, **params):
    """The path of a scene XML for ``source``: ``source`` itself when it is a scene (then
    ``field``, ``isovalue`` and ``save_scene`` must be None), else the scene made for the data
    file, written to ``save_scene`` (kept; replaced only with ``force``) or to a temporary
    folder (removed when the block ends). Prints the field and isovalue it picked (and that
    ``sets_isovalue``, the caller's option, sets it). ``offer``: as
    :func:`~mi_amr.plugin.autoscene.data_scene` takes it (the field read for the pick, handed
    to the preparations that will load the scene)."""
    if is_scene_file(source):
        given = [n for n, v in (("--field", field), ("--isovalue", isovalue),
                                ("--mode", params.get("mode")), ("--save-scene", save_scene),
                                ("--allow-nonfinite", params.get("allow_nonfinite")))
                 if v is not None]
        if given:
            keep = "".join(
                f", and {what} with its amr_iso parameter {name}"
                for option, what, name in (("--mode", "the mode", "mode"),
                                           ("--allow-nonfinite", "NaN/Inf values kept",
                                            "allow_nonfinite")) if option in given)
            verb = "applies" if len(given) == 1 else "apply"
            raise AMRError(f"{source} is a scene file: {', '.join(given)} {verb} to data "
                           f"files only (set a scene's <default>s with -D NAME=VALUE{keep})")
        yield Path(source)
        return
    if save_scene is not None:
        save_scene = check_output(save_scene, suffixes=(SCENE_SUFFIX,), overwrite=force,
                                  make_folders=True)
    made = make_scene(source, field=field, isovalue=isovalue, resolution=resolution, spp=spp,
                      say=say, framed_values=framed_values, sets_isovalue=sets_isovalue,
                      offer=offer, **params)
    if save_scene is not None:
        with replacing(save_scene) as tmp:
            Path(tmp).write_text(made.xml())
        say(f"wrote the scene {save_scene}")
        yield save_scene
        return
    with tempfile.TemporaryDirectory(prefix="mi_amr_scene_") as folder:
        path = Path(folder) / f"{Path(made.path).name}{SCENE_SUFFIX}"
        path.write_text(made.xml())
        yield path


def make_scene(source, *, field=None, isovalue=None, resolution=None, spp=None, say=print,
               framed_values=None, sets_isovalue: str = "--isovalue", offer=None, **params):
    """The :class:`~mi_amr.plugin.autoscene.DataScene` of ``source``, with what was picked
    printed (and that ``sets_isovalue``, the caller's option: ``--isovalue`` on the command
    line, ``isovalue=`` in Python, sets it)."""
    from mi_amr.plugin.autoscene import RESOLUTION, SPP, data_scene

    t0 = time.perf_counter()
    made = data_scene(source, field, isovalue, resolution=resolution or RESOLUTION,
                      spp=spp or SPP, framed_values=framed_values, offer=offer, **params)
    seconds = time.perf_counter() - t0
    how = "given"
    if made.picked:
        others = ", ".join(f"{v:.6g}" for v in made.suggested[1:])
        how = "picked from the histogram" + (f"; also try {others}" if others else "") + \
            f"; {sets_isovalue} sets it"
    say(f"{made.path}: field {made.field}, isovalue {made.isovalue:.6g} ({how}); scene made "
        f"in {seconds:.1f} s")
    if made.band_picked and made.params.get("mode") == "volume":
        say(f"  volume band width {made.params['band_width']:.6g} (picked from the histogram; "
            f"the scene's band_width parameter sets it)")
    return made


def movie_inputs(sources, files=None):
    """``(scene or first data file, time series)`` of ``movie``'s arguments: one scene file
    (with ``--files`` as given), or data files and globs (the series, in natural order)."""
    from mi_amr.workflows.movie.spec import expand_files

    sources = list(sources)
    scenes = [s for s in sources if is_scene_file(s)]
    if scenes and len(sources) == 1:
        return sources[0], files
    if scenes:
        raise AMRError(f"movie: give one scene file, or data files; got {', '.join(sources)}")
    if files:
        raise AMRError("movie: --files goes with a scene file; list the data files themselves "
                       "instead")
    try:
        series = expand_files(sources)
    except AMRError as e:           # (its messages name the --files option)
        raise AMRError(str(e).replace("--files: ", "movie: ", 1)) from None
    return series[0], series
