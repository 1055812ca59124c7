"""The pytest plugin (torm.testing.plugin): a smoke trial below its threshold is a FAILED test (not a setup
ERROR), and ``--torm-record failures`` keeps the recording of the failed test only, named in its report."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

SMOKE_TESTS = textwrap.dedent("""
    import pytest

    @pytest.mark.torm_smoke(scenario="rw1", method="oracle", min_success=1.01)  # no trial can reach 101 %
    def test_impossible(torm_smoke_result):
        pass

    @pytest.mark.torm_smoke(scenario="rw1", method="oracle", min_success=0.0)
    def test_always(torm_smoke_result):
        assert torm_smoke_result["n_objects"] == 1
""")


@pytest.mark.slow
def test_threshold_miss_is_a_failure_and_only_its_recording_is_kept(tmp_path):
    (tmp_path / "test_smoke_fixture.py").write_text(SMOKE_TESTS)
    rec_dir = tmp_path / "recs"
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rA",
                           "--torm-record", "failures", "--torm-record-dir", str(rec_dir), "test_smoke_fixture.py"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=900,
                          env={**os.environ, "MUJOCO_GL": "egl"})
    out = done.stdout
    assert "1 failed, 1 passed" in out and "error" not in out.split("short test summary")[-1].lower(), out[-3000:]
    assert "FAILED test_smoke_fixture.py::test_impossible" in out and "success rate 1.00 < 1.01" in out
    kept = sorted(p.name for p in rec_dir.glob("*.rrd"))
    assert len(kept) == 1 and "test_impossible" in kept[0], kept
    assert "torm recordings" in out and kept[0] in out
