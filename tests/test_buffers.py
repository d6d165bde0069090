"""A volume's values held once: per-grid arrays that are views of one aligned buffer are mapped
by the device as they are (no copy), and a preparation keeps nothing of the velocity its
derived fields came from."""

import gc
import os
import sys
import weakref

import drjit as dr
import numpy as np
import pytest

from mi_amr.core import buffers
from mi_amr.kernels import prepared
from mi_amr.kernels.device import DeviceVolume
from mi_amr.core.kdtree import KDTree
from mi_amr.synthetic import datasets

M = dr.llvm.ad


def views(buf, sizes):
    out, at = [], 0
    for n in sizes:
        out.append(buf[at:at + n].reshape(n, 1, 1))
        at += n
    return out


def test01_joined_finds_the_buffer_of_consecutive_views():
    buf = buffers.aligned_full(40, 1.5, np.float32)
    assert buf.ctypes.data % buffers.ALIGN == 0 and np.all(buf == 1.5)
    whole = buffers.joined(views(buf, [10, 20, 10]), np.float32)
    assert whole is not None and whole.ctypes.data == buf.ctypes.data and whole.size == 40
    part = buffers.joined(views(buf, [10, 20]), np.float32)
    assert part.size == 30 and part.ctypes.data == buf.ctypes.data


def test02_joined_refuses_what_a_copy_would_differ_from():
    buf = buffers.aligned_empty(40, np.float32)
    a, b, c = views(buf, [10, 20, 10])
    assert buffers.joined([a, c], np.float32) is None                 # a gap
    assert buffers.joined([b, a], np.float32) is None                 # out of order
    assert buffers.joined([a, b], np.float64) is None                 # another dtype
    assert buffers.joined([buf[::2]], np.float32) is None             # not contiguous
    assert buffers.joined([b], np.float32) is None                    # starts unaligned (40 B)
    assert buffers.joined([b], np.float32, aligned=False).ctypes.data == b.ctypes.data


def test03_derived_fields_are_mapped_by_the_device_without_a_copy():
    vol = datasets.sphere_wake("small", progress=False)
    vol, derived = prepared.needed_fields(vol, "q_criterion", "speed")
    assert derived and set(vol.field_names) == {"q_criterion", "speed"}
    dev = DeviceVolume(vol, KDTree(vol), "q_criterion", "speed", m=M)
    for name, arr in (("q_criterion", dev.values), ("speed", dev.color_values)):
        flat = buffers.joined([g.fields[name] for g in vol.grids], np.float32)
        assert flat is not None, name
        host = arr.numpy()
        assert host.ctypes.data == flat.ctypes.data, name     # the same memory
        np.testing.assert_array_equal(
            host, np.concatenate([g.fields[name].ravel() for g in vol.grids]))


def test04_values_not_in_one_buffer_are_copied_once():
    vol = datasets.sphere_wake("small", progress=False)
    vol, _ = prepared.needed_fields(vol, "q_criterion", "speed")
    grids = list(vol.grids)
    for g in grids:                                # each grid's own float64 array
        g.fields["q_criterion"] = g.fields["q_criterion"].astype(np.float64)
    dev = DeviceVolume(vol, KDTree(vol), "q_criterion", m=M)
    expect = np.concatenate([g.fields["q_criterion"].ravel() for g in grids]).astype(np.float32)
    np.testing.assert_array_equal(dev.values.numpy(), expect)


def test05_the_velocity_is_freed_once_the_caller_drops_its_volume():
    vol = datasets.sphere_wake("small", progress=False)
    watched = [weakref.ref(g.fields[n]) for g in vol.grids[:5] for n in ("vx", "vy", "vz")]
    out, _ = prepared.needed_fields(vol, "q_criterion", "speed")
    del vol
    gc.collect()
    assert all(w() is None for w in watched)
    assert set(out.field_names) == {"q_criterion", "speed"}
    assert not any(k[1] in ("vx", "vy", "vz") for k in out.level_caches.values)


def test05b_a_volume_holding_just_the_fields_is_given_back_as_it_is():
    """needed_fields of a volume that holds exactly the fields asked for (a derivation's result,
    asked again by the preparation) gives that volume back, not a copy of every grid's record;
    one holding more, or the same fields in another order, is narrowed to a new volume."""
    vol = datasets.sphere_wake("small", progress=False)
    out, _ = prepared.needed_fields(vol, "q_criterion", "speed")
    again, derived = prepared.needed_fields(out, "q_criterion", "speed")
    assert again is out and not derived
    swapped, _ = prepared.needed_fields(out, "speed", "q_criterion")
    assert swapped is not out and swapped.field_names == ("speed", "q_criterion")
    narrowed, _ = prepared.needed_fields(out, "speed", None)
    assert narrowed is not out and narrowed.field_names == ("speed",)

def test06_level_values_of_a_file_read_whole_are_views_of_what_was_read(tmp_path):
    from mi_amr.core import levels
    from mi_amr.readers import load

    path = tmp_path / "wake.npz"
    datasets.sphere_wake("small", progress=False).save(path)
    vol = load(path, fields=["vx"])
    for level in range(vol.num_levels):
        flat = levels.level_values(vol, level, "vx")
        grids = levels.level_index(vol, level).grids
        np.testing.assert_array_equal(
            flat, np.concatenate([vol.grids[g].fields["vx"].ravel() for g in grids]))
        assert np.shares_memory(flat, vol.grids[grids[0]].fields["vx"])


def test07_level_values_follow_a_replaced_array_unless_fields_are_fixed():
    from mi_amr.core import levels

    vol = datasets.sphere_wake("small", progress=False)
    first = levels.level_values(vol, 0, "vx").copy()
    g = levels.level_index(vol, 0).grids[0]
    n = vol.grids[g].num_cells
    with levels.fields_fixed(vol):
        vol.grids[g].fields["vx"] = vol.grids[g].fields["vx"] + 1.0
        np.testing.assert_array_equal(levels.level_values(vol, 0, "vx"), first)
    again = levels.level_values(vol, 0, "vx")
    np.testing.assert_array_equal(again[:n], first[:n] + np.float32(1.0))
    np.testing.assert_array_equal(again[n:], first[n:])



def test07b_adopted_level_values_are_the_grids_own_arrays():
    """A level buffer a caller vouches for is cached only where the volume's grids hold the very
    arrays given, of the buffer's dtype and size; afterwards a replaced array is followed."""
    from mi_amr.core import levels

    vol = datasets.sphere_wake("small", progress=False)
    ids = np.flatnonzero(vol.levels == 1)
    flat = np.concatenate([vol.grids[g].fields["vx"].ravel() for g in ids])
    own = [vol.grids[g].fields["vx"] for g in ids]
    copies = [a.copy() for a in own]
    levels.adopt_level_values(vol, 1, "vx", flat.copy(), copies)      # not the grids' arrays
    levels.adopt_level_values(vol, 1, "vx", flat.astype(np.float64), own)      # another dtype
    levels.adopt_level_values(vol, 1, "vx", flat[:-1], own)                     # another size
    assert (1, "vx") not in vol.level_caches.values
    views_of = np.empty_like(flat)
    at = 0
    for g in ids:                          # the level's arrays made views of one buffer
        n = vol.grids[g].num_cells
        views_of[at:at + n] = vol.grids[g].fields["vx"].ravel()
        vol.grids[g].fields["vx"] = views_of[at:at + n].reshape(vol.grids[g].shape)
        at += n
    levels.adopt_level_values(vol, 1, "vx", views_of,
                              [vol.grids[g].fields["vx"] for g in ids])
    assert levels.level_values(vol, 1, "vx") is views_of
    g = ids[0]
    vol.grids[g].fields["vx"] = vol.grids[g].fields["vx"] + 1.0
    again = levels.level_values(vol, 1, "vx")
    assert again is not views_of
    np.testing.assert_array_equal(again[:vol.grids[g].num_cells],
                                  views_of[:vol.grids[g].num_cells] + np.float32(1.0))


def test07c_a_load_finds_its_buffers_without_a_look_at_each_grid(tmp_path, monkeypatch):
    """Reading a file, deriving Q and the speed and making the device arrays never looks at the
    grids' arrays one by one to find the buffer they lie in (the address of each of thousands
    of arrays: a noticeable part of a time step's load): the reader, the derivation and the
    snapshot say which buffers they made, and the device's flat field is the derivation's
    buffer, mapped."""
    from mi_amr.core import levels
    from mi_amr.readers import load

    path = tmp_path / "wake.npz"
    datasets.sphere_wake("small", progress=False).save(path)
    looked = []
    real = buffers.joined

    def counted(arrays, dtype, aligned=True):
        arrays = list(arrays)
        looked.append(len(arrays))
        return real(arrays, dtype, aligned)

    monkeypatch.setattr(levels, "joined", counted)
    vol = load(path, fields=["vx", "vy", "vz"], level_buffers={"vx", "vy", "vz"})
    vol, _ = prepared.needed_fields(vol, "q_criterion", "speed", m=M, consume=True)
    dev = DeviceVolume(vol, KDTree(vol), "q_criterion", "speed", m=M)
    assert looked and max(looked) <= vol.num_levels < len(vol.grids)
    for name, arr in (("q_criterion", dev.values), ("speed", dev.color_values)):
        flat = np.concatenate([g.fields[name].ravel() for g in vol.grids])
        np.testing.assert_array_equal(arr.numpy(), flat)
        assert levels.volume_values(vol, name).ctypes.data == arr.numpy().ctypes.data, name


_REUSE = """
import ctypes, sys
import numpy as np
from mi_amr.core import memory

class Info(ctypes.Structure):   # glibc's struct mallinfo2
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                                                "usmblks", "fsmblks", "uordblks", "fordblks",
                                                "keepcost")]

libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = Info
assert memory.keep_freed_memory() == (sys.argv[1] == "keep")
before = libc.mallinfo2().hblkhd
a = np.ones(3 << 20)            # 24 MB, below MMAP_THRESHOLD
mapped = libc.mallinfo2().hblkhd - before
del a
print(mapped >> 20, libc.mallinfo2().fordblks >> 20)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test20_freed_memory_is_kept_for_the_next_array():
    """After memory.keep_freed_memory(), a 24 MB array comes from the heap and, once freed,
    stays there for the next one; glibc's default maps it from the system (fresh pages, slow
    to touch) and gives it back. MI_AMR_KEEP_MEMORY=0 leaves the default."""
    import subprocess

    def megabytes(mode, **env):
        out = subprocess.run([sys.executable, "-c", _REUSE, mode], capture_output=True,
                             text=True, check=True, env={**os.environ, **env})
        return [int(x) for x in out.stdout.split()[-2:]]

    mapped, kept = megabytes("keep")
    assert mapped == 0 and kept >= 24
    mapped, kept = megabytes("default", MI_AMR_KEEP_MEMORY="0")
    assert mapped >= 24 and kept < 24


_ADVICE = """
import numpy as np
from mi_amr.core import memory

memory.keep_freed_memory()
print(int(np._core.multiarray._get_madvise_hugepage()))
"""


def test20b_a_load_turns_numpys_huge_page_advice_off():
    """memory.keep_freed_memory() (every load calls it) stops NumPy advising huge pages for its
    new arrays, whose first write can stall on memory compaction; MI_AMR_KEEP_MEMORY=0 leaves
    NumPy's default (advice on)."""
    import subprocess

    np_core = getattr(np, "_core", None)
    if np_core is None or not hasattr(np_core.multiarray, "_get_madvise_hugepage"):
        pytest.skip("this NumPy has no huge-page switch")

    def advice(**env):
        env = {k: v for k, v in {**os.environ, **env}.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
        out = subprocess.run([sys.executable, "-c", _ADVICE], capture_output=True, text=True,
                             check=True, env=env)
        return int(out.stdout.split()[-1])

    assert advice() == 0
    assert advice(MI_AMR_KEEP_MEMORY="0") == 1


_RELEASE = """
import sys
import numpy as np
from mi_amr.core import memory

def resident():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 >> 20

memory.keep_freed_memory()
held = [np.ones(3 << 20) for _ in range(8)]     # 8 x 24 MB from the heap, touched
top = np.ones(3 << 20)                          # above them: the heap's top stays in use
del held
before = resident()
released = memory.release_freed_memory()
print(int(released), before - resident())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test21_freed_memory_is_given_back_when_asked():
    """memory.release_freed_memory() gives back the freed heap that keep_freed_memory() keeps,
    also below an array still in use (what a large load does before its brick pools);
    MI_AMR_KEEP_MEMORY=0 leaves the allocator alone."""
    import subprocess

    def run(**env):
        out = subprocess.run([sys.executable, "-c", _RELEASE], capture_output=True, text=True,
                             check=True, env={**os.environ, **env})
        return [int(x) for x in out.stdout.split()[-2:]]

    released, megabytes = run()
    assert released == 1 and megabytes >= 150
    released, megabytes = run(MI_AMR_KEEP_MEMORY="0")
    assert released == 0
