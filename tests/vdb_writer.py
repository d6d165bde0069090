"""Write .vdb test files with the real OpenVDB library (run by the system Python, not the venv).

Usage: ``/usr/bin/python3 vdb_writer.py spec.json``. The spec maps an output path to a list of
grids; each grid is a dict with:

* ``type``: ``float``, ``vec3s`` or ``bool``; ``name``; ``voxel_size`` h; ``translation``
  (default ``h / 2`` per axis, so voxel ``i`` covers ``[h i, h (i + 1)]``) or ``matrix`` (a 4x4
  index-to-world matrix, rows ``[a, b, c, 0]``, translation in the last row);
* ``lo`` (index of the first voxel) and ``shape``: the dense block written with
  ``copyFromArray``, filled with :func:`components` of each voxel centre's world position
  (float grids: component ``component``, default 0); ``tolerance`` is passed on (default 0:
  values equal to the background, 0, become inactive);
* optional ``half`` (saveFloatAsHalf), ``zero_box`` (``[lo, hi]`` inclusive
  index box set to 0 before writing), ``fills`` (``[[lo, hi, value, active], ...]``:
  ``grid.fill``, which makes tiles where it can), ``sets`` (``[[[i, j, k], value], ...]``: single
  active voxels), ``instance_of`` (index of an earlier grid of the same file whose tree this grid
  shares, via ``grid.copy()``).

Prints ``{path: [file_compression metadata of each grid]}`` as JSON.
"""

import json
import sys

import numpy as np

try:
    import pyopenvdb as vdb
except ImportError:  # OpenVDB >= 12 names the module openvdb
    import openvdb as vdb


def linear(x, y, z):
    """The test field: a linear function of world position."""
    return 1.0 + 2.0 * x + 3.0 * y - 5.0 * z


def components(x, y, z):
    """The three components of the vector test field (float grids take one of them)."""
    f = linear(x, y, z)
    return f, f + 100.0, -f


def transform(spec):
    h = spec["voxel_size"]
    if "matrix" in spec:
        return vdb.createLinearTransform(spec["matrix"])
    t = spec.get("translation", [h / 2] * 3)
    return vdb.createLinearTransform([[h, 0, 0, 0], [0, h, 0, 0], [0, 0, h, 0],
                                      [t[0], t[1], t[2], 1]])


def block(spec):
    """Values of the dense block ``lo .. lo + shape`` at the voxel centres (world)."""
    lo, shape = np.array(spec["lo"]), spec["shape"]
    xform = transform(spec)
    idx = np.stack(np.meshgrid(*[lo[a] + np.arange(shape[a]) for a in range(3)],
                               indexing="ij"), axis=-1).reshape(-1, 3)
    world = np.array([xform.indexToWorld(tuple(int(c) for c in ijk)) for ijk in idx])
    f = np.stack(components(world[:, 0], world[:, 1], world[:, 2]), axis=-1)
    f = f.reshape(tuple(shape) + (3,))
    if spec["type"] == "vec3s":
        return f.astype(np.float32)
    if spec["type"] == "bool":
        return f[..., 0] > 0
    return f[..., spec.get("component", 0)].astype(np.float32)


def make_grid(spec, made):
    if "instance_of" in spec:
        grid = made[spec["instance_of"]].copy()
        grid.transform = transform(spec)
        grid.name = spec["name"]
        return grid
    kind = {"float": vdb.FloatGrid, "vec3s": vdb.Vec3SGrid, "bool": vdb.BoolGrid}[spec["type"]]
    grid = kind()
    grid.name = spec["name"]
    grid.transform = transform(spec)
    if "shape" in spec:
        values = block(spec)
        if "zero_box" in spec:
            (a, b) = np.array(spec["zero_box"]) - np.array(spec["lo"])
            values[a[0]:b[0] + 1, a[1]:b[1] + 1, a[2]:b[2] + 1] = 0
        tolerance = spec.get("tolerance", 0)
        if spec["type"] == "vec3s":
            tolerance = (tolerance,) * 3
        if spec["type"] == "bool":
            grid.copyFromArray(values, ijk=tuple(spec["lo"]))
        else:
            grid.copyFromArray(values, ijk=tuple(spec["lo"]), tolerance=tolerance)
    for lo, hi, value, active in spec.get("fills", []):
        grid.fill(tuple(lo), tuple(hi), value, active)
    accessor = grid.getAccessor()
    for ijk, value in spec.get("sets", []):
        accessor.setValueOn(tuple(ijk), value)
    if spec.get("half"):
        grid.saveFloatAsHalf = True
    return grid


def main():
    with open(sys.argv[1]) as f:
        files = json.load(f)
    report = {}
    for path, specs in files.items():
        made = []
        for spec in specs:
            made.append(make_grid(spec, made))
        vdb.write(path, made)
        report[path] = [g.metadata.get("file_compression", "")
                        for g in vdb.readAllGridMetadata(path)]
    json.dump(report, sys.stdout)


if __name__ == "__main__":
    main()
