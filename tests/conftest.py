"""Shared builders of small, valid AMR hierarchies (world boxes given by hand, so every expected
value in the tests can be derived from them).

All spacings here are powers of two, so grid faces, cell centres and hat-support boundaries are
exact binary fractions and "a point exactly on a face" means exactly.
"""

import os

import numpy as np
import pytest

# No test reads or writes the user's snapshot folder (~/.cache/mi_amr), and none depends on what
# an earlier run left there; tests/test_snapshot.py points it at a temporary folder.
os.environ["MI_AMR_CACHE"] = "off"

from mi_amr import AMRVolume  # noqa: E402

# tests/mutants/replay.py runs test files against mutated copies; it is no test itself.
collect_ignore = ["mutants"]


def grid(level, lo, hi, h, fn=None, names=("f",)):
    """A grid record covering the world box ``[lo, hi]`` with cells of size ``h`` (a float);
    each field is ``fn(centres)`` (``centres`` shaped ``(nx, ny, nz, 3)``), or zeros."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    shape = tuple(int(n) for n in np.round((hi - lo) / h))
    axes = [lo[a] + (np.arange(shape[a]) + 0.5) * h for a in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    fields = {}
    for name in names:
        fields[name] = np.zeros(shape) if fn is None else np.asarray(fn(centres), dtype=np.float64)
    return {"level": level, "origin": tuple(lo), "spacing": h, "fields": fields}


# World boxes of the reference hierarchy: two level-0 grids sharing the face x = 4; level-1
# grids spanning that face, touching each other at y = 4, and one apart; level-2 grids inside
# them, one spanning the level-1 face y = 4, one touching its parent's faces.
LEVEL0 = [((0, 0, 0), (4, 8, 8)), ((4, 0, 0), (8, 8, 8))]
LEVEL1 = [((2, 2, 2), (6, 4, 4)), ((2, 4, 2), (4, 6, 4)), ((5, 5, 5), (7, 7, 7))]
LEVEL2 = [((3, 2.5, 2.5), (5, 3.5, 3.5)), ((3, 3.5, 2.5), (4, 4.5, 3.5)),
          ((5.5, 5, 6), (6.5, 6, 7))]


def reference_grids(ratios=(2, 2), fn=None, names=("f",)):
    """The reference hierarchy (3 levels, 8 grids) with level-0 cells of size 1."""
    h = [1.0, 1.0 / ratios[0], 1.0 / (ratios[0] * ratios[1])]
    out = []
    for level, boxes in enumerate((LEVEL0, LEVEL1, LEVEL2)):
        out += [grid(level, lo, hi, h[level], fn, names) for lo, hi in boxes]
    return out


def stretched(grids, scale=(1.0, 0.5, 2.0)):
    """``grids`` (mapping records) with every x, y, z length scaled by ``scale``: cells that
    are not cubes, so a per-axis mix-up shows."""
    return [dict(g, origin=tuple(np.multiply(g["origin"], scale)),
                 spacing=tuple(np.multiply(g["spacing"], scale))) for g in grids]


def random_grids(seed, *, num_levels=3, ratios=(2, 2), base=(8, 6, 6), tries=12, fn=None):
    """A random valid hierarchy: level 0 is ``base`` cells (size 1) cut into slabs along x;
    each finer level gets up to ``tries`` random boxes, each inside one grid of the level above
    and on its lattice, kept when it does not overlap the boxes already chosen."""
    rng = np.random.default_rng(seed)
    cuts = np.unique(np.concatenate([[0, base[0]], rng.integers(1, base[0], 2)]))
    boxes = [[(np.array([a, 0, 0]), np.array([b, base[1], base[2]]))
              for a, b in zip(cuts[:-1], cuts[1:])]]
    h = [1.0]
    for level in range(1, num_levels):
        r = ratios[level - 1]
        h.append(h[-1] / r)
        chosen = []
        for _ in range(tries):
            plo, phi = boxes[level - 1][rng.integers(len(boxes[level - 1]))]
            ext = np.round((phi - plo) / h[level - 1]).astype(int)
            size = np.array([rng.integers(1, min(n, 3) + 1) for n in ext])
            start = np.array([rng.integers(0, n - s + 1) for n, s in zip(ext, size)])
            lo = plo + start * h[level - 1]
            hi = lo + size * h[level - 1]
            if all(np.any(hi <= clo) or np.any(lo >= chi) for clo, chi in chosen):
                chosen.append((lo, hi))
        boxes.append(chosen)
    return [grid(level, lo, hi, h[level], fn) for level in range(num_levels)
            for lo, hi in boxes[level]]


@pytest.fixture
def reference_volume():
    return AMRVolume.from_grids(reference_grids())


# ---------------------------------------------------------------------- Mitsuba (imported lazily)

VARIANT = "llvm_ad_rgb"


def use_variant():
    """Set the tests' Mitsuba variant and register ``amr_iso`` for it; skip when Mitsuba or
    the variant is missing. (Imported here, not at collection, so the NumPy-only tests run
    without Mitsuba.)"""
    mi = pytest.importorskip("mitsuba")
    pytest.importorskip("drjit")
    if VARIANT not in mi.variants():
        pytest.skip(f"Mitsuba variant {VARIANT} is not available")
    mi.set_variant(VARIANT)
    import mi_amr

    mi_amr.register()
    return mi


# The vectorised variants a test that takes ``each_variant`` or ``backend`` runs over, where
# this machine has them (Mitsuba's practice: variant fixtures filtered by what is installed).
VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")


def present_variants() -> list:
    """The :data:`VARIANTS` built into Mitsuba whose Dr.Jit backend this machine runs (CUDA
    only with a GPU); none without Mitsuba."""
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError:
        return []
    backends = {"llvm": dr.JitBackend.LLVM, "cuda": dr.JitBackend.CUDA}
    return [v for v in VARIANTS
            if v in mi.variants() and dr.has_backend(backends[v.split("_")[0]])]


def pytest_generate_tests(metafunc):
    """One run of a test per present variant where it takes ``each_variant`` or ``backend``."""
    for name in ("each_variant", "backend"):
        if name in metafunc.fixturenames:
            metafunc.parametrize(name, present_variants() or [None], indirect=True)


@pytest.fixture
def each_variant(request):
    """Mitsuba with this run's variant set (and ``amr_iso`` registered for it); the tests'
    :data:`VARIANT` set again afterwards."""
    if request.param is None:
        pytest.skip("no vectorised Mitsuba variant on this machine")
    mi = pytest.importorskip("mitsuba")
    mi.set_variant(request.param)
    import mi_amr

    mi_amr.register()
    yield mi
    mi.set_variant(VARIANT)


@pytest.fixture
def backend(request):
    """The Dr.Jit backend module (``drjit.llvm.ad``, ``drjit.cuda.ad``) of this run's variant:
    kernel tests that need no Mitsuba object take it as their ``m``."""
    if request.param is None:
        pytest.skip("no vectorised Mitsuba variant on this machine")
    import drjit as dr

    return getattr(dr, request.param.split("_")[0]).ad


@pytest.fixture(scope="module")
def variant():
    """The tests' variant, set for the module and set again afterwards (a test may switch)."""
    mi = use_variant()
    yield mi
    mi.set_variant(VARIANT)


@pytest.fixture(scope="module")
def scene_data_ready(variant):
    """The data files of the repository's scenes (made once, then reused)."""
    from mi_amr.workflows import project

    project.ensure_scene_data(verbose=False)


def kernels_compiled(fn):
    """Run ``fn()`` and return ``(its result, JIT kernels not found in memory)``: compiled now,
    or loaded from Dr.Jit's disk cache because no kernel like it ran before in this process."""
    import drjit as dr

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    try:
        out = fn()
        dr.sync_thread()
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    jit = [k for k in history if k["type"] == dr.KernelType.JIT]
    return out, sum(1 for k in jit if not k.get("cache_hit", False) or k.get("cache_disk", False))


def small_scene(folder, integrator: str, res: int, defaults: str = ""):
    """Write ``folder/scene.xml``: an ``amr_iso`` integrator whose parameters are the XML
    ``integrator``, a ``res`` x ``res`` perspective view of the unit cube (1 spp, RGB), a
    directional light and a sphere below the volume; ``defaults``: ``<default>`` lines."""
    import textwrap

    text = f"""
    <scene version="3.0.0">
        {defaults}
        <integrator type="amr_iso" id="integrator">
            {integrator}
        </integrator>
        <sensor type="perspective" id="sensor">
            <float name="fov" value="30"/>
            <transform name="to_world">
                <lookat origin="1.6, -0.9, 1.4" target="0.5, 0.5, 0.5" up="0, 0, 1"/>
            </transform>
            <sampler type="independent"><integer name="sample_count" value="1"/></sampler>
            <film type="hdrfilm">
                <integer name="width" value="{res}"/><integer name="height" value="{res}"/>
                <string name="pixel_format" value="rgb"/>
            </film>
        </sensor>
        <emitter type="directional" id="light">
            <vector name="direction" value="-0.4, 0.5, -1.0"/>
            <rgb name="irradiance" value="2.5"/>
        </emitter>
        <shape type="sphere" id="ball">
            <point name="center" value="0.5, 0.5, -0.6"/><float name="radius" value="0.3"/>
        </shape>
    </scene>"""
    path = folder / "scene.xml"
    path.write_text(textwrap.dedent(text))
    return path
