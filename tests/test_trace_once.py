"""Every symbolic loop of a frame is traced once. Dr.Jit traces a loop's body a second time,
without them, when some of its state variables never change in it (values the body only
reads, a colour that a shadow ray never adds to, a second array's sums where there is
none), so those must not be loop state: each loop names what it only reads
(``dr.hint(..., exclude=[...])``) and leaves out what it would not change. A loop traced
twice costs its trace time twice (and the loops inside it four times), on every frame.

Counted by wrapping ``drjit.while_loop``, which the code that ``@dr.syntax`` writes looks up
when it runs.
"""

from collections import Counter

import pytest

from conftest import small_scene
from mi_amr.synthetic import datasets

RES = 12


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    yield


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("trace_once")
    vol = datasets.sphere(8)
    vol.save(folder / "a.npz")
    return folder / "a.npz"


def scene_file(folder, data, extra):
    return small_scene(folder, f'<string name="filename" value="{data}"/>'
                               f'<string name="field" value="f"/>{extra}', RES)


COLOUR = ('<string name="color_field" value="f"/>'
          '<string name="colormap" value="0.1: 0 0 1, 0.3: 0 1 0, 0.5: 1 0 0"/>')
SCENES = {
    "surface": '<string name="isovalue" value="0.3"/>' + COLOUR,
    "surface, no colour field": '<string name="isovalue" value="0.3"/>',
    "surface, translucent layers": '<string name="isovalue" value="0.25, 0.35"/>'
                                   '<string name="iso_opacity" value="0.5, 0.6"/>'
                                   '<string name="layers" value="composite"/>',
    "surface, one shadow ray a sample": '<string name="isovalue" value="0.25, 0.35"/>'
                                        '<string name="iso_opacity" value="0.5, 0.6"/>'
                                        '<string name="layers" value="one_shadow"/>',
    "surface, one layer a sample": '<string name="isovalue" value="0.25, 0.35"/>'
                                   '<string name="iso_opacity" value="0.5, 0.6"/>'
                                   '<string name="layers" value="stochastic"/>',
    "surface, adaptive": '<string name="isovalue" value="0.3"/>'
                         '<string name="method" value="adaptive"/>' + COLOUR,
    "surface, bisect": '<string name="isovalue" value="0.3"/>'
                       '<string name="method" value="bisect"/>',
    "volume": '<string name="isovalue" value="0.3"/><string name="mode" value="volume"/>'
              '<float name="band_width" value="0.02"/>' + COLOUR,
    "volume, three bands": '<string name="isovalue" value="0.2, 0.3, 0.4"/>'
                           '<string name="mode" value="volume"/>'
                           '<string name="band_width" value="0.005, 0.01, 0.015"/>',
    "volume, adaptive": '<string name="isovalue" value="0.3"/>'
                        '<string name="mode" value="volume"/>'
                        '<string name="method" value="adaptive"/>',
    "surface, uniform": '<string name="isovalue" value="0.3"/>'
                        '<string name="method" value="uniform"/>' + COLOUR,
    "volume, uniform": '<string name="isovalue" value="0.3"/>'
                       '<string name="mode" value="volume"/>'
                       '<string name="method" value="uniform"/>',
    "volume, bisect": '<string name="isovalue" value="0.3"/>'
                      '<string name="mode" value="volume"/>'
                      '<string name="method" value="bisect"/>' + COLOUR,
}


def traced_loops(mi, path):
    """Per loop label, how many times its body was traced in each call, over the first
    frame of the scene at ``path`` (which traces everything)."""
    import drjit as dr

    from mi_amr.plugin.scene import load_scene

    scene = load_scene(path)
    real = dr.while_loop
    counts = []

    def counting(state, cond, body, *args, label=None, **kw):
        calls = Counter()

        def counted(*a):
            calls["body"] += 1
            return body(*a)

        try:
            return real(state, cond, counted, *args, label=label, **kw)
        finally:
            counts.append((label, calls["body"]))

    dr.while_loop = counting
    try:
        img = mi.render(scene, seed=0)
    finally:
        dr.while_loop = real
    dr.eval(img)
    return counts


@pytest.mark.parametrize("name", list(SCENES))
def test01_each_loop_of_a_frame_is_traced_once(variant, data, tmp_path, name):
    counts = traced_loops(variant, scene_file(tmp_path, data, SCENES[name]))
    assert counts, "no symbolic loop was traced"
    twice = sorted({label for label, n in counts if n != 1})
    assert not twice, f"{name}: loop(s) traced more than once: {twice}"


def test02_the_loops_checked_are_those_of_the_frames(variant, data, tmp_path):
    """The scenes above run every loop of the surface and volume marches (so a loop whose
    state grows a constant is caught)."""
    seen = set()
    for i, extra in enumerate(SCENES.values()):
        folder = tmp_path / str(i)
        folder.mkdir()
        seen |= {label for label, _ in traced_loops(variant, scene_file(folder, data, extra))}
    want = {"seek", "dual_planes", "level_cubics", "first_crossing", "transmit", "composite",
            "level_gradients", "first_crossing_sampled", "bisect", "composite_sampled",
            "bisect_band", "front_to_back", "pick_one", "one_shadow_ray", "levels", "locate"}
    assert want <= seen, f"not run: {sorted(want - seen)}"
