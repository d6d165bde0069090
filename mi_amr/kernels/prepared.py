"""A volume made ready for rendering: the fields it needs loaded or derived, the kd-tree built
and everything flattened onto the device. Shared by the integrator and :func:`mi_amr.trace`.

Loading reads only the fields a scene uses (a derived field reads just the velocity).
Preparing the same file twice in one session (a :class:`Preparations`: the integrator's, for a
benchmark sweep or a movie) reuses the work;
across processes (a render after the viewer, every Dask worker of a movie) a snapshot on disk
does (:mod:`mi_amr.kernels.snapshot`).
"""

from __future__ import annotations

import os
import time
from collections import OrderedDict
from dataclasses import dataclass, replace

import drjit as dr

from mi_amr import params
from mi_amr.core import memory
from mi_amr.core.derive import DERIVED_FIELDS, velocity_fields
from mi_amr.kernels import derive as device_derive
from mi_amr.kernels import snapshot
from mi_amr.kernels.device import DeviceVolume, build_bricks, field_values
from mi_amr.kernels.kdsteps import DeviceSteps
from mi_amr.errors import AMRError
from mi_amr.core.kdtree import KDTree



class PreparedVolume:
    """``volume`` with ``field`` (and ``color_field``) present, its kd-tree and device arrays.

    ``m`` is the Dr.Jit backend module of the kernels that will read it. ``timings`` holds the
    seconds each step took (``derive``, ``tree``, ``device``; ``read`` when loaded from a file
    by :func:`prepare_file`; ``snapshot`` when read back from one, see :meth:`restore`).
    """

    def __init__(self, volume, field: str, color_field: str | None = None, *,
                 leaf_cells: int = params.default("leaf_cells"), m=None,
                 by: "Preparations | None" = None):
        """``by``: the :class:`Preparations` it is made for, whose ``report`` is told each
        step as it ends (one line of text), and whose kept preparation of the same grids
        (:meth:`Preparations.like`) gives its kd-tree, not built again (the tree is made from
        the grids alone); or None."""
        self._make(volume, (field, color_field), (leaf_cells, m or dr.llvm.ad), by, None)

    @classmethod
    def from_pools(cls, grids, fields, released, *, setup, by=None) -> "PreparedVolume":
        """The preparation, for the basis blend alone (:attr:`keeps_fields` False), of the
        volume that :func:`without_fields` gave: ``grids`` (its hierarchy alone), ``released``
        (its brick pools and value ranges); ``fields``: ``(field, color_field)``; ``setup``:
        ``(leaf_cells, m)``; ``by`` as for the constructor."""
        self = cls.__new__(cls)
        self._make(grids, fields, setup, by, released)
        return self

    def _make(self, volume, fields, setup, by, released) -> None:
        """The constructor's work (and :meth:`from_pools`'s, ``released`` not None)."""
        (field, color_field), (leaf_cells, m) = fields, setup
        memory.keep_freed_memory()
        clock = time.perf_counter()
        self.timings = {}
        self.report = report = by.report if by is not None else None
        derived = False
        if released is None:
            volume, derived = needed_fields(volume, field, color_field, m=m)
        bricks, self.value_ranges = released or (None, None)
        self.volume = volume
        self.field = field
        self.color_field = color_field or field
        clock = self._lap("derive", clock, quiet=not derived)
        like = by.like(volume, leaf_cells) if by is not None else None
        if like is not None and volume.adopt_hierarchy(like.volume):
            self.tree = KDTree.from_arrays(volume, like.tree.arrays())
            clock = self._lap("tree", clock, quiet=True)
            if report is not None:
                report("  kd-tree of the same grids reused")
        else:
            self.tree = KDTree(self.volume, leaf_cells=leaf_cells, device=DeviceSteps(m))
            clock = self._lap("tree", clock)
        if volume.num_cells >= memory.RELEASE_CELLS:
            # The pools are new mappings, which cannot reuse what the derivation's kernels and
            # the tree freed: handed back first, that memory is not part of the load's peak.
            dr.flush_malloc_cache()
            memory.release_freed_memory()
        self.device = DeviceVolume(self.volume, self.tree, field, self.color_field, m=m,
                                   bricks=bricks)
        self._lap("device", clock)

    @property
    def keeps_fields(self) -> bool:
        """Whether the field's values are kept (on the host and the device): False for a
        preparation made for the basis blend alone, which holds its brick pools instead
        (:func:`without_fields`)."""
        return self.field in self.volume.field_names

    def value_range(self, name: str):
        """``(min, max)`` of the finite values of field ``name`` (the field or the colour
        field), over all cells: :meth:`AMRVolume.value_range
        <mi_amr.core.volume.AMRVolume.value_range>`, taken before the values were dropped
        where they were."""
        if self.value_ranges is not None and name in self.value_ranges:
            return self.value_ranges[name]
        return self.volume.value_range(name)

    @classmethod
    def restore(cls, snap, *, m=None, report=None) -> "PreparedVolume":
        """The preparation held by a snapshot (what :meth:`SnapshotCache.load
        <mi_amr.kernels.snapshot.SnapshotCache.load>` returns), its kd-tree
        and brick pools as they were saved, the device arrays mapped from them."""
        volume, tree_state, bricks, ranges, meta = snap
        self = cls.__new__(cls)
        self.volume, self.field, self.color_field = volume, meta["field"], meta["color_field"]
        self.value_ranges = {k: tuple(v) for k, v in meta["value_ranges"].items()} \
            if "value_ranges" in meta else None
        self.tree = KDTree.from_arrays(volume, tree_state)
        self.device = DeviceVolume(volume, self.tree, self.field, self.color_field,
                                   m=m or dr.llvm.ad, bricks=bricks)
        self.device.host_ranges.update(ranges)
        self.timings = {}
        self.report = report
        return self

    def search_ready(self, basis: bool) -> None:
        """Make the leaf search's records for a reconstruction now (its value ranges, on the
        device: :meth:`DeviceVolume.node_ranges`), not while a frame is traced; the ranges,
        when they were not there yet, timed as ``ranges``."""
        clock = time.perf_counter()
        fresh = ("basis" if basis else "finest") not in self.device.host_ranges
        self.device.node_search(basis)
        if fresh:
            self._lap("ranges", clock)

    def _lap(self, name, since, quiet=False):
        now = time.perf_counter()
        self.timings[name] = now - since
        if not quiet and self.report is not None:
            self.report(f"{_STEPS[name]} in {now - since:.2f} s")
        return now


_STEPS = {"derive": "  derived fields", "tree": "  kd-tree", "device": "  device arrays",
          "ranges": "  leaf value ranges",
          "snapshot": "  prepared volume read back from its snapshot"}


def needed_fields(volume, field: str, color_field: str | None, m=None, consume=False):
    """``(volume, derived)``: ``volume`` with exactly the fields ``field`` and ``color_field``
    (derived from the velocity where it lacks them, by Dr.Jit kernels on backend ``m``
    (:mod:`mi_amr.kernels.derive`), on the host when ``m`` is None; ``derived``: some were),
    arrays shared.
    Whatever else ``volume`` held is not referenced by the result, so a caller that drops its
    own reference frees it (the velocity a derived field was computed from). ``consume``: the
    caller gives ``volume`` up, and a velocity that neither field shows is dropped from it
    level by level during the derivation (:func:`mi_amr.core.derive.derive`)."""
    wanted = [f for f in dict.fromkeys([field, color_field]) if f is not None]
    missing = [f for f in wanted if f not in volume.field_names]
    derivable = [f for f in missing if f in DERIVED_FIELDS]
    unknown = [f for f in missing if f not in DERIVED_FIELDS]
    if unknown:
        raise AMRError(f"{volume.source_prefix()}unknown field(s) {unknown}: the volume holds "
                       f"{list(volume.field_names)}; derived fields are "
                       f"{list(DERIVED_FIELDS)}")
    if derivable:
        consume = consume and not set(velocity_fields(volume)) & set(wanted)
    if derivable and m is not None:
        volume = device_derive.derive(volume, *derivable, m=m, consume=consume)
    elif derivable:
        from mi_amr.core.derive import derive
        volume = derive(volume, *derivable, consume=consume)
    if list(volume.field_names) == wanted:      # (already so: no copy of every grid's record)
        return volume, bool(derivable)
    return volume.select_fields(wanted), bool(derivable)


def without_fields(volume, field: str, color_field: str | None, m):
    """``(grids, (bricks, value_ranges))``: the brick pools of ``field`` and ``color_field``
    made from ``volume`` (:func:`~mi_amr.kernels.device.build_bricks`), the fields' value
    ranges (:meth:`AMRVolume.value_range <mi_amr.core.volume.AMRVolume.value_range>`) and
    ``volume`` without its fields (the grids, leaf masks and level tables shared): what a
    :class:`PreparedVolume` for the basis blend alone is made from (its ``released``). A
    caller that drops its own reference to ``volume`` frees the fields' values before the
    kd-tree is built, so the pools and the values are never held with the tree."""
    names = [f for f in dict.fromkeys([field, color_field]) if f is not None]
    values = [field_values(m, volume, name) for name in names]
    bricks = build_bricks(m, volume, values)
    ranges = {name: volume.value_range(name) for name in names}
    return volume.select_fields([]), (bricks, ranges)


def fields_to_read(field: str, color_field: str | None, available, source=None) -> list:
    """Names to read from disk (the file ``source``, named in an error) for a scene showing
    ``field`` coloured by ``color_field``: stored fields as they are, the velocity components
    for a derived one."""
    out = []
    for name in (field, color_field):
        if name is None:
            continue
        if name in available or name not in DERIVED_FIELDS:
            out.append(name)  # an unknown name is reported by the reader
        else:
            out.extend(_velocity_names(available, name, source))
    return list(dict.fromkeys(out))


def _velocity_names(available, derived: str, source) -> list:
    from mi_amr.core.derive import VELOCITY_NAMES

    for names in VELOCITY_NAMES:
        if all(n in available for n in names):
            return list(names)
    where = f"{source}: " if source is not None else ""
    raise AMRError(f"{where}'{derived}' is derived from three velocity components, which it "
                   f"lacks (looked for {', '.join('/'.join(n) for n in VELOCITY_NAMES)}); it "
                   f"holds {', '.join(available)}")


class Preparations:
    """The volumes one session (an integrator class, a benchmark) prepared from files: the
    last :attr:`SIZE` kept by file (and its modification time), fields, leaf size and backend,
    and given again. A new preparation first forgets the oldest kept one when :attr:`SIZE`
    are kept, so that the memory that one frees (where nothing else holds it) is reused by
    the new load rather than new memory touched. ``report``: a callable told each step of a
    preparation as it ends (one line of text; the command line prints them, so a load of
    several seconds shows what it is doing), or None. ``cache``: the
    :class:`~mi_amr.kernels.snapshot.SnapshotCache` its preparations read and write, or None
    for the one ``$MI_AMR_CACHE`` describes at the time of each preparation.
    ``series_steps``: how many files the series this session shows has (a movie sets it); a
    preparation writes its snapshot only where that many would fit the cache.
    ``keep_fields``: every preparation keeps its fields' values, also where the scene reads
    the brick pools alone (the viewer's histograms and value ranges read them)."""

    SIZE = 3

    def __init__(self, report=None, cache: snapshot.SnapshotCache | None = None):
        self.report = report
        self.cache = cache
        # The files of the series this session shows one after the other (a movie's): a
        # step's snapshot is written only where that many fit the cache (_write_snapshot).
        self.series_steps = 1
        self.keep_fields = False
        self._kept: "OrderedDict[tuple, PreparedVolume]" = OrderedDict()
        self._offer = None

    def clear(self) -> None:
        """Forget every volume prepared so far (the next preparation reads its file), and a
        volume offered."""
        self._kept.clear()
        self._offer = None

    def offer(self, path, volume, allow_nonfinite: bool = False) -> None:
        """Hand over ``volume``, just read from the file ``path`` (with NaN and Inf values kept
        where ``allow_nonfinite``) and holding the fields it holds as that file's
        preparation would make them (a data file's scene reads its field to pick the
        isovalue): the next :meth:`prepare` of that file, unchanged since, takes the fields it
        needs from it instead of reading (and deriving) them again, where it holds them all
        and no snapshot does. One volume is held at a time, until a preparation of its file."""
        path = os.path.abspath(path)
        self._offer = (path, _stamp(path), bool(allow_nonfinite), volume)

    def retain(self, paths) -> None:
        """Forget every kept volume prepared from a file not among ``paths`` (a time series'
        movie, which shows each file once: the steps it has shown are not shown again)."""
        keep = {os.path.abspath(p) for p in paths}
        for key in [k for k in self._kept if k[0] not in keep]:
            del self._kept[key]

    def say(self, text: str) -> None:
        if self.report is not None:
            self.report(text)

    def prepare(self, path, field: str, color_field: str | None = None, *, m=None,
                how: "LoadOptions" = None) -> PreparedVolume:
        """:func:`prepare_file` (``how``: a :class:`LoadOptions`, its defaults where None),
        given again while it is kept. Where ``how.keep_fields`` is False (a scene that reads
        the brick pools alone) the fields' values are kept only where :attr:`keep_fields`
        says so, and a kept preparation that keeps them serves it too."""
        how = how or LoadOptions()
        path = os.path.abspath(path)
        stamp = _stamp(path)
        how = replace(how, keep_fields=how.keep_fields or self.keep_fields)
        keys = [(path, stamp, field, color_field, how.leaf_cells, getattr(m, "__name__", None),
                 bool(how.allow_nonfinite), kept) for kept in (True, how.keep_fields)]
        for key in dict.fromkeys(reversed(keys)):
            if key in self._kept:
                self.take_offer(path, how.allow_nonfinite)      # (not needed: dropped)
                self._kept.move_to_end(key)
                return self._kept[key]
        while self._kept and len(self._kept) >= self.SIZE:
            self._kept.popitem(last=False)
        prepared = prepare_file(path, field, color_field, m=m, by=self, how=how)
        self._kept[keys[1]] = prepared
        return prepared

    def like(self, volume, leaf_cells: int) -> "PreparedVolume | None":
        """The newest kept preparation of ``leaf_cells`` whose volume has the
        :meth:`same hierarchy <mi_amr.core.volume.AMRVolume.same_hierarchy>` as ``volume``
        (another time step of unchanged grids, or the same file with other fields), or
        None: a preparation of ``volume`` takes its kd-tree."""
        for prepared in reversed(list(self._kept.values())):
            if prepared.tree.leaf_cells == leaf_cells and \
                    prepared.volume.same_hierarchy(volume):
                return prepared
        return None

    def take_offer(self, path, allow_nonfinite: bool = False):
        """The volume :meth:`offer` holds for the file ``path`` (absolute) read as it is now
        and as ``allow_nonfinite`` says, or None; a preparation of that file takes it or drops
        it."""
        if self._offer is None or self._offer[0] != path:
            return None
        path, stamp, nonfinite, volume = self._offer
        self._offer = None
        return volume if (stamp, nonfinite) == (_stamp(path), bool(allow_nonfinite)) else None


def _stamp(path: str) -> int:
    """The modification time (ns) of the file or folder ``path``; one error where there is
    none."""
    try:
        return os.stat(path).st_mtime_ns
    except OSError:
        raise AMRError(f"{path}: no such file or folder") from None


@dataclass(frozen=True)
class LoadOptions:
    """How :func:`prepare_file` reads and prepares a file: the kd-tree's leaf size
    (``leaf_cells``, cells), whether NaN and Inf values are kept as missing data
    (``allow_nonfinite``, as :func:`mi_amr.load` takes it; else a file holding them is
    refused), and whether the fields' values are kept (``keep_fields``; else only the brick
    pools the basis blend reads: :func:`without_fields`)."""

    leaf_cells: int = params.default("leaf_cells")
    allow_nonfinite: bool = False
    keep_fields: bool = True


def prepare_file(path, field: str, color_field: str | None = None, *, m=None,
                 by: "Preparations | None" = None,
                 how: LoadOptions = LoadOptions()) -> PreparedVolume:
    """Load ``path`` (only what is needed) and prepare it as ``how`` says, or read it back
    from its snapshot. ``by``: the :class:`Preparations` it is made for, whose ``report``
    hears each step and
    whose ``cache`` holds the snapshots (without one: no report, and the cache that
    ``$MI_AMR_CACHE`` describes, see :meth:`SnapshotCache.from_env
    <mi_amr.kernels.snapshot.SnapshotCache.from_env>`); a volume offered to it
    (:meth:`Preparations.offer`) gives the fields where it holds every one needed and no
    snapshot is read. Keeps nothing: a :class:`Preparations` keeps what it prepared and gives
    it again."""
    path = os.path.abspath(path)
    if not os.path.exists(path):
        raise AMRError(f"{path}: no such file or folder")
    report = by.report if by is not None else None
    say = report or (lambda text: None)
    cache = by.cache if by is not None and by.cache is not None else \
        snapshot.SnapshotCache.from_env()
    snap_key = snapshot.entry_key(path, field, color_field, how.leaf_cells,
                                  how.allow_nonfinite, how.keep_fields) \
        if cache.enabled else None
    memory.keep_freed_memory()          # for the read's buffers, or the snapshot's
    t0 = time.perf_counter()
    offered = by.take_offer(path, how.allow_nonfinite) if by is not None else None
    snap = cache.load(snap_key) if snap_key else None
    if snap is not None:
        prepared = PreparedVolume.restore(snap, m=m, report=report)
        prepared._lap("snapshot", t0)
    else:
        prepared = _prepare_from_file(path, (field, color_field), how, m, by, offered)
        if snap_key:
            _write_snapshot(cache, snap_key, prepared, by.series_steps if by else 1, say)
    if snap_key:
        prepared.device.on_new_ranges = lambda kind, host: cache.save_ranges(snap_key, kind,
                                                                             host)
    return prepared


def _write_snapshot(cache, key, prepared, steps: int, say) -> None:
    """Write ``prepared``'s snapshot as entry ``key`` of ``cache``, unless it is one step of a
    series of ``steps`` files whose snapshots would not all fit the cache: their entries
    would evict each other (and the cache's other entries) before a second run could read
    them, and writing one adds a third or more to a step's preparation."""
    if steps > 1 and not cache.holds(prepared, steps):
        say(f"  no snapshot written: the series' {steps:,} steps would not fit the snapshot "
            f"cache's {cache.limit / 1e9:.2f} GB (MI_AMR_CACHE_GB)")
        return
    t0 = time.perf_counter()
    if cache.save(key, prepared):
        say(f"  snapshot written in {time.perf_counter() - t0:.2f} s")


def _prepare_from_file(path, fields, how: LoadOptions, m, by,
                       offered=None) -> PreparedVolume:
    """Read what ``fields`` (``(field, color_field)``) need from ``path`` and prepare it;
    from the volume ``offered`` (read from ``path``) instead where it holds them all. ``by``:
    the :class:`Preparations` it is made for (its report; a volume it keeps of the same
    grids gives its kd-tree, :meth:`Preparations.like`), or None."""
    from mi_amr.readers import available_fields, load

    field, color_field = fields
    report = by.report if by is not None else None
    say = report or (lambda text: None)
    wanted = [f for f in dict.fromkeys(fields) if f is not None]
    if offered is not None and all(f in offered.field_names for f in wanted):
        volume = offered.select_fields(wanted)
        say(f"  {os.path.basename(path)} ({', '.join(wanted)}: {volume.num_cells:,} cells, "
            f"{len(volume.grids):,} grids) already read")
        offered = None                  # (this frame's hold on its fields)
        t0 = time.perf_counter()
        volume, released = _released(volume, fields, how, m)
        return _timed(_made(volume, fields, released, how, m, by), time.perf_counter() - t0)
    names = fields_to_read(field, color_field, available_fields(path), path)
    t0 = time.perf_counter()
    volume = load(path, fields=names, level_buffers=set(names) - {field, color_field},
                  allow_nonfinite=how.allow_nonfinite)
    read = time.perf_counter() - t0
    say(f"  read {os.path.basename(path)} ({', '.join(names)}: {volume.num_cells:,} cells, "
        f"{len(volume.grids):,} grids) in {read:.2f} s")
    # A kept volume of the same grids lends its level tables to the derivation (and its
    # kd-tree to the preparation).
    same = by.like(volume, how.leaf_cells) if by is not None else None
    if same is not None:
        volume.adopt_hierarchy(same.volume)
    # Derived here, so that the velocity read for it is freed before the kd-tree and the
    # device arrays are built (a third of the peak memory of a large load), and level by
    # level during the derivation (read with a buffer per level for that).
    t0 = time.perf_counter()
    volume, derived = needed_fields(volume, field, color_field, m=m or dr.llvm.ad,
                                    consume=True)
    derive_s = time.perf_counter() - t0
    if derived:
        say(f"{_STEPS['derive']} in {derive_s:.2f} s")
    # (The volume rebound here: where the fields are dropped, nothing holds them any more.)
    t0 = time.perf_counter()
    volume, released = _released(volume, fields, how, m)
    pools_s = time.perf_counter() - t0
    return _timed(_made(volume, fields, released, how, m, by), pools_s, (read, derive_s))


def _made(volume, fields, released, how: LoadOptions, m, by) -> PreparedVolume:
    """The :class:`PreparedVolume` of ``volume`` for ``fields``, from its pools where
    ``released`` (:func:`_released`)."""
    if released is None:
        return PreparedVolume(volume, *fields, leaf_cells=how.leaf_cells, m=m, by=by)
    return PreparedVolume.from_pools(volume, fields, released,
                                     setup=(how.leaf_cells, m or dr.llvm.ad), by=by)


def _released(volume, fields, how: LoadOptions, m):
    """``(volume, released)`` for a :class:`PreparedVolume` of ``fields`` (``(field,
    color_field)``): ``volume`` as it is and None where ``how.keep_fields``, else
    :func:`without_fields` (the brick pools made, the fields dropped, so that the kd-tree is
    built with the pools alone held where the caller rebinds its ``volume``)."""
    if how.keep_fields:
        return volume, None
    field, color_field = fields
    volume, _ = needed_fields(volume, field, color_field, m=m or dr.llvm.ad)
    return without_fields(volume, field, color_field, m or dr.llvm.ad)


def _timed(prepared: PreparedVolume, pools_s: float, read_derive=None):
    """``prepared``, the seconds :func:`_released` took (the brick pools of a preparation
    without values; next to nothing otherwise) counted in its device step, and the file's read
    and derivation (``read_derive``, seconds) in its :attr:`~PreparedVolume.timings`."""
    steps = prepared.timings
    steps["device"] = steps.get("device", 0.0) + pools_s
    if read_derive is not None:
        prepared.timings = {"read": read_derive[0], **steps, "derive": read_derive[1]}
    return prepared
