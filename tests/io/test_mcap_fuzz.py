"""The fuzz test of the MCAP reader: damaged variants of a small log (tests/mcap_fuzz.py).

`make test` reads 40 seeded variants; `make fuzz` reads CVSLAM_FUZZ_VARIANTS (default 600)
and prints the tally (figures in BENCHMARKS.md, "MCAP fuzz").
"""

from __future__ import annotations

import logging
import os

from tests.mcap_fuzz import fuzz
from tests.synth import write_stereo_log


def test_damaged_logs_give_a_clean_error_or_a_warning_never_a_traceback(tmp_path, caplog):
    n = int(os.environ.get("CVSLAM_FUZZ_VARIANTS", "40"))
    seed = int(os.environ.get("CVSLAM_FUZZ_SEED", "2026"))
    synth = write_stereo_log(tmp_path / "log.mcap", n_frames=8, chunk_size=8 * 1024)
    caplog.set_level(logging.ERROR, logger="cvslam")
    result = fuzz(synth.path, tmp_path, n, seed)
    print(f"\nMCAP fuzz: {n} variants (seed {seed}): {dict(sorted(result.outcomes.items()))}")
    assert not result.bad, "\n".join(result.bad[:20])
    assert sum(result.outcomes.values()) == n
    # both honest outcomes occur: damage that leaves something usable is read on past
    assert result.outcomes["warned"] > 0 and result.outcomes["error"] > 0
