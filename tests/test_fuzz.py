"""Damaged inputs end as AMRError, a damaged snapshot cache as a fresh preparation: a small fixed
set of the fuzz harness's cases (``tests/fuzz_inputs.py``, ``tests/fuzz_cache.py``; run it with
more cases and other seeds by hand)."""

import pytest

import fuzz_inputs

SEEDS = (0, 1)
NPZ_CASES = 50          # per seed: raw byte mutations of a small .npz
HEADER_CASES = 30       # per seed: mutations of a small plotfile's Header
CACHE_CASES = 16        # seed 0: damaged, planted and linked snapshot caches


@pytest.mark.slow
def test01_mutated_npz_files_and_plotfile_headers_give_only_amr_errors():
    tallies = fuzz_inputs.fuzz(NPZ_CASES, HEADER_CASES, SEEDS, jobs=2)
    text = fuzz_inputs.report(tallies)
    assert tallies["npz"].cases == NPZ_CASES * len(SEEDS), text
    assert tallies["header"].cases == HEADER_CASES * len(SEEDS), text
    for t in tallies.values():
        assert (t.exceptions, t.hangs, t.crashes) == (0, 0, 0), text
    # The mutations do reach the parsers: most cases are refused, not read as if intact.
    for t in tallies.values():
        assert t.statuses.get("amrerror", 0) > t.cases // 2, text


@pytest.mark.slow
def test02_damaged_planted_and_linked_caches_are_prepared_afresh_and_touch_nothing():
    """Flipped bits, truncated arrays, planted files and pickles, bad JSON, a user's folders
    and links pointing outside: 0 exceptions, tracebacks, hangs, wrong results, pickles run,
    and 0 files changed or removed outside the cache's own folders."""
    tallies = fuzz_inputs.fuzz(0, 0, (0,), cache=CACHE_CASES, jobs=2)
    text = fuzz_inputs.report(tallies)
    t = tallies["cache"]
    assert t.cases == CACHE_CASES, text
    assert (t.exceptions, t.hangs, t.crashes, t.others) == (0, 0, 0, 0), text
    # The damage reaches the cache: most cases drop the entry and prepare afresh.
    assert sum(o.detail == "prepared afresh" for o in t.outcomes) > CACHE_CASES // 2, text


# ---------------------------------------------------------------------- the viewer's protocol

PROTOCOL_CASES = 60     # random requests (seed 0), besides the fixed malformed ones


@pytest.mark.slow
def test03_viewer_requests_get_one_line_errors_and_a_slow_reader_is_bounded(variant):
    """The viewer's protocol cases (``fuzz_inputs.fuzz_protocol``): the fixed malformed
    messages, random requests and a client that never reads: no traceback, no hang, no crash,
    nothing written outside the output folder."""
    tallies = fuzz_inputs.fuzz_protocol(PROTOCOL_CASES, (0,))
    text = fuzz_inputs.report(tallies)
    t = tallies["protocol"]
    assert t.cases == len(fuzz_inputs.FIXED_MESSAGES) + PROTOCOL_CASES + 1, text
    assert (t.exceptions, t.hangs, t.crashes) == (0, 0, 0), text
