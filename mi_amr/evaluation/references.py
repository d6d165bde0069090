"""Exact reference renders and hit buffers, and how other renders are scored against them.

``python -m mi_amr reference --regenerate`` renders every scene of :data:`SCENES` with the
``exact`` method and the ``basis`` reconstruction at :data:`RESOLUTION` and :data:`SPP` samples
per pixel into ``reference/NAME.exr``, and stores the primary-ray hit buffers (depth, normal,
hit mask, for one ray through each pixel centre) in ``reference/NAME_hits.npz``. Nothing else
writes there; tests only read.

Hit buffers come from :func:`hit_buffers`, which runs the integrator's own kernels on camera
rays through pixel centres: ``t`` is the distance along the (unit) camera ray to the first
visible isosurface crossing (inf where none, or where a mesh is in front).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_amr.errors import AMRError
from mi_amr.workflows import project

SCENES = ("analytic_sphere", "analytic_torus", "analytic_spike", "sphere_wake", "plt_eb_3d")
RESOLUTION = (256, 256)
SPP = 16


@dataclass
class HitBuffers:
    """Per pixel (``(H, W)`` arrays; ``normal`` is ``(H, W, 3)``, world space)."""

    t: np.ndarray
    hit: np.ndarray
    normal: np.ndarray
    cell: float          # finest cell width of the volume, in world units along the ray

    def save(self, path):
        np.savez_compressed(path, t=self.t, hit=self.hit, normal=self.normal,
                            cell=np.array(self.cell))

    @classmethod
    def load(cls, path):
        with np.load(path, allow_pickle=False) as f:
            return cls(t=f["t"], hit=f["hit"], normal=f["normal"], cell=float(f["cell"]))


def reference_path(name: str, kind: str = "image") -> Path:
    """``reference/NAME.exr`` (``kind="image"``) or ``reference/NAME_hits.npz`` (``"hits"``)."""
    return project.reference_dir() / (f"{name}.exr" if kind == "image" else f"{name}_hits.npz")


def scene_path(name: str) -> Path:
    return project.scenes_dir() / f"{name}.xml"


def available(name: str) -> bool:
    """Whether the data of scene ``name`` can be found (``plt_eb_3d`` needs ../shared)."""
    if name == "plt_eb_3d":
        return (project.shared_dir() / "data" / "amrex" / "plt_eb_3d").exists()
    return True


def pixel_rays(sensor):
    """One camera ray through each pixel centre (world space, unit directions), row-major."""
    import drjit as dr
    import mitsuba as mi

    w, h = sensor.film().crop_size()
    idx = dr.arange(mi.UInt32, w * h)
    pos = mi.Vector2f(mi.Float(idx % w) + 0.5, mi.Float(idx // w) + 0.5) / mi.Vector2f(w, h)
    ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), pos, mi.Point2f(0.5, 0.5))
    return ray


def hit_buffers(scene) -> HitBuffers:
    """Primary-ray hits of the scene's ``amr_iso`` integrator, one ray per pixel centre."""
    import drjit as dr
    import mitsuba as mi

    from mi_amr.kernels.jitter import stable_jitter
    from mi_amr.kernels.ray import RayContext
    from mi_amr.kernels.surface import first_crossing
    from mi_amr.kernels.reconstruct import reconstruct

    integ = scene.integrator()
    if not hasattr(integ, "prep"):
        raise AMRError("hit_buffers(): the scene's integrator is not amr_iso")
    sensor = scene.sensors()[0]
    w, h = sensor.film().crop_size()
    idx = dr.arange(mi.UInt32, w * h)
    ray = pixel_rays(sensor)
    si = scene.ray_intersect(ray)
    t_mesh = dr.select(si.is_valid(), si.t, dr.inf)
    m = integ.m
    o, d = integ.frame.ray_to_volume(integ.m, ray.o, ray.d)
    jitter = stable_jitter(m, m.UInt32(idx))
    cfg = integ.config()
    c = first_crossing(RayContext(integ.dev, cfg, o, d, m.Float(0.0), m.Float(t_mesh),
                                  m.Bool(True)), jitter)
    _, grad = reconstruct(integ.dev, cfg.basis, dr.fma(d, c.t, o), integ.dev.arrays(cfg.basis),
                          c.hit)
    n = dr.normalize(integ.frame.to_scene @ mi.Normal3f(grad.x, grad.y, grad.z))
    dr.eval(c.t, c.hit, n)
    hit = c.hit.numpy().reshape(h, w).astype(bool)
    t = np.where(hit, c.t.numpy().reshape(h, w), np.inf)
    normal = np.stack([n.x.numpy(), n.y.numpy(), n.z.numpy()], axis=-1).reshape(h, w, 3)
    normal[~hit] = np.nan
    scale = integ.frame.scale()
    return HitBuffers(t=t, hit=hit, normal=normal, cell=integ.dev.min_h_host * scale)


@dataclass
class Score:
    """How a render's hits compare with the reference's (fractions of pixels; depth errors in
    finest cells; normal errors in degrees)."""

    missed: float
    false: float
    depth_mean: float
    depth_p99: float
    normal_mean: float
    rmse: float

    def as_dict(self):
        return dict(self.__dict__)


def score(buffers: HitBuffers, ref: HitBuffers, image=None, ref_image=None) -> Score:
    """Missed hits (reference hit, render none), false hits (the reverse), depth and normal
    errors where both hit (normals compared up to sign, as surfaces are shaded two-sided), and
    the image RMSE when both images are given."""
    both = buffers.hit & ref.hit
    n = buffers.hit.size
    depth = np.abs(buffers.t[both] - ref.t[both]) / ref.cell
    cosang = np.abs(np.sum(buffers.normal[both] * ref.normal[both], axis=-1))
    angle = np.degrees(np.arccos(np.clip(cosang, 0.0, 1.0)))
    rmse = float(np.sqrt(np.mean((image - ref_image) ** 2))) if image is not None else np.nan
    return Score(missed=float(np.sum(ref.hit & ~buffers.hit)) / n,
                 false=float(np.sum(buffers.hit & ~ref.hit)) / n,
                 depth_mean=float(depth.mean()) if depth.size else 0.0,
                 depth_p99=float(np.percentile(depth, 99)) if depth.size else 0.0,
                 normal_mean=float(np.nanmean(angle)) if angle.size else 0.0,
                 rmse=rmse)


def write_exr(path, image):
    """Write ``image`` (``(H, W, 3)``, linear RGB) as an EXR, atomically: a failed write leaves
    the reference that was there."""
    import mitsuba as mi

    from mi_amr.core.atomic import replacing

    bitmap = mi.Bitmap(np.asarray(image, dtype=np.float32),
                       pixel_format=mi.Bitmap.PixelFormat.RGB)
    with replacing(path) as tmp:
        bitmap.write(str(tmp))


def read_exr(path) -> np.ndarray:
    import mitsuba as mi

    return np.array(mi.Bitmap(str(path)), dtype=np.float32)


def render(scene, spp: int, seed: int = 0) -> np.ndarray:
    import drjit as dr
    import mitsuba as mi

    img = mi.render(scene, spp=spp, seed=seed)
    dr.eval(img)
    return np.array(img, dtype=np.float32)


def regenerate(names=SCENES, out_dir=None, variant: str = "llvm_ad_rgb") -> list:
    """Write the reference images and hit buffers (the only code that writes ``reference/``)."""
    import mitsuba as mi

    mi.set_variant(variant)
    from mi_amr.plugin.integrator import register
    from mi_amr.plugin.scene import load_scene

    register()
    project.ensure_scene_data()
    out_dir = Path(out_dir or project.reference_dir())
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name in names:
        if not available(name):
            print(f"skipping {name}: its data is not here")
            continue
        scene = load_scene(scene_path(name), resx=RESOLUTION[0], resy=RESOLUTION[1], spp=SPP,
                           method="exact", reconstruction="basis")
        image = render(scene, SPP)
        write_exr(out_dir / f"{name}.exr", image)
        hit_buffers(scene).save(out_dir / f"{name}_hits.npz")
        written += [out_dir / f"{name}.exr", out_dir / f"{name}_hits.npz"]
        print(f"wrote {name}: {out_dir / (name + '.exr')} and its hit buffers")
    return written
