"""Damaged inputs end as AMRError: a small fixed set of the fuzz harness's cases
(``tests/fuzz_inputs.py``; run it with more cases and other seeds by hand)."""

import pytest

import fuzz_inputs

SEEDS = (0, 1)
NPZ_CASES = 50          # per seed: raw byte mutations of a small .npz
HEADER_CASES = 30       # per seed: mutations of a small plotfile's Header


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


# ---------------------------------------------------------------------- the viewer's protocol

PROTOCOL_CASES = 60     # random requests (seed 0), besides the fixed malformed ones


@pytest.mark.slow
def test02_viewer_requests_get_one_line_errors_and_a_slow_reader_is_bounded(variant):
    """The viewer's protocol cases (``fuzz_inputs.fuzz_protocol``): the fixed malformed
    messages, random requests and a client that never reads: no traceback, no hang, no crash,
    nothing written outside the output folder."""
    tallies = fuzz_inputs.fuzz_protocol(PROTOCOL_CASES, (0,))
    text = fuzz_inputs.report(tallies)
    t = tallies["protocol"]
    assert t.cases == len(fuzz_inputs.FIXED_MESSAGES) + PROTOCOL_CASES + 1, text
    assert (t.exceptions, t.hangs, t.crashes) == (0, 0, 0), text
