"""Volume mode with several opacity bands, one per isovalue, each with its own colour, width and
peak (translucent nested shells)."""

import textwrap

import numpy as np
import pytest

from mi_amr import AMRError
from mi_amr.synthetic import datasets


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    yield


def scene(folder, isovalues, colors, widths="0.01", peaks="0.6", method="exact"):
    path = folder / "bands.xml"
    path.write_text(textwrap.dedent(f"""
        <scene version="3.0.0">
            <integrator type="amr_iso">
                <string name="filename" value="sphere.npz"/>
                <string name="field" value="f"/>
                <string name="isovalue" value="{isovalues}"/>
                <string name="iso_color" value="{colors}"/>
                <string name="mode" value="volume"/>
                <string name="method" value="{method}"/>
                <string name="band_width" value="{widths}"/>
                <string name="band_peak" value="{peaks}"/>
                <boolean name="shadows" value="false"/>
            </integrator>
            <sensor type="perspective">
                <float name="fov" value="30"/>
                <transform name="to_world">
                    <lookat origin="0.5, -1.6, 0.5" target="0.5, 0.5, 0.5" up="0, 0, 1"/>
                </transform>
                <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
                <film type="hdrfilm"><integer name="width" value="32"/>
                    <integer name="height" value="32"/>
                    <string name="pixel_format" value="rgb"/></film>
            </sensor>
            <emitter type="directional"><vector name="direction" value="0.2, 1, -0.3"/>
                <rgb name="irradiance" value="3"/></emitter>
        </scene>"""))
    return path


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("bands")
    datasets.sphere(16).save(out / "sphere.npz")
    return out


def render(mi, path):
    from mi_amr.plugin.scene import load_scene

    return np.array(mi.render(load_scene(path), seed=0), dtype=np.float64)


@pytest.mark.parametrize("method", ["exact", "adaptive"])
def test01_three_nested_bands_show_their_own_colours(variant, folder, method):
    """Shells at |p - c| = 0.12, 0.22, 0.32 in red, green and blue, on black: near the rim a
    ray meets the outer (blue) shell only, through the centre all three (so red shows)."""
    mi = variant
    img = render(mi, scene(folder, "0.12, 0.22, 0.32", "1 0 0; 0 1 0; 0 0 1", method=method))
    ring = np.hypot(*np.meshgrid(np.arange(32) - 15.5, np.arange(32) - 15.5))
    centre, rim = img[ring < 3], img[(ring > 9) & (ring < 12)]
    assert img[..., 0].max() > 0.05 and img[..., 1].max() > 0.05 and img[..., 2].max() > 0.05
    assert rim[:, 2].mean() > 0.02
    assert rim[:, 0].mean() < 0.01 * rim[:, 2].mean() and rim[:, 1].mean() < 0.01 * rim[:, 2].mean()
    assert centre[:, 0].mean() > 0.1 * centre[:, 2].mean()


@pytest.mark.parametrize("widths,peaks,message", [
    ("0.01, 0.02", "0.6", "'band_width' needs 1 or 3 values"),
    ("-0.01", "0.6", "'band_width' needs 1 or 3 values in"),
    ("0.01", "0.6, 0.5", "'band_peak' needs 1 or 3 values")])
def test03_band_lists_of_the_wrong_length_or_sign_are_refused(variant, folder, widths, peaks,
                                                               message):
    from mi_amr.plugin.scene import load_scene

    path = scene(folder, "0.12, 0.22, 0.32", "1 0 0", widths=widths, peaks=peaks)
    with pytest.raises(AMRError, match=message):
        load_scene(path)


def test04_overlapping_bands_are_refused_at_load_and_through_traverse(variant, folder):
    """Two bands whose supports share values: one error naming both isovalues and what to
    change, when the scene loads and when mi.traverse moves an isovalue into another band."""
    mi = variant
    from mi_amr.plugin.scene import load_scene

    with pytest.raises(AMRError, match=r"isovalues 0.12 .* and 0.13 .* overlap; narrow "
                                       r"'band_width' or 'band_support'"):
        load_scene(scene(folder, "0.12, 0.13, 0.32", "1 0 0; 0 1 0; 0 0 1"))
    loaded = load_scene(scene(folder, "0.12, 0.22, 0.32", "1 0 0; 0 1 0; 0 0 1"))
    params = mi.traverse(loaded)
    key = next(k for k in params.keys() if k.endswith("isovalue"))
    params[key] = mi.Float([0.12, 0.125, 0.32])
    with pytest.raises(AMRError, match="overlap"):
        params.update()
