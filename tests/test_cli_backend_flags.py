"""``--backend real`` plumbing of ``torm trial`` / ``torm bench``: clear errors, no motion without hardware."""

from __future__ import annotations

import argparse

from torm.cli import main
from torm.commands.bench import trial_overrides


def test_real_backend_without_hardware_config_names_the_fix(capsys, monkeypatch):
    monkeypatch.delenv("TORM_HARDWARE_CONFIG", raising=False)
    assert main(["trial", "--backend", "real"]) == 2
    assert "--hardware-config" in capsys.readouterr().err


def test_real_backend_with_unreachable_rosbridge_names_host_and_port(tmp_path, capsys):
    hw = tmp_path / "hw.yaml"
    hw.write_text(f"host: 127.0.0.1\nport: 9\nconnect_timeout_s: 0.5\ncommand_log: {tmp_path}/log.jsonl\n")
    assert main(["trial", "--backend", "real", "--hardware-config", str(hw), "--arm-robot"]) == 2
    err = capsys.readouterr().err
    assert "127.0.0.1:9" in err


def test_bench_flags_become_trial_overrides():
    args = argparse.Namespace(backend="real", robot_config="my_robot.yaml", hardware_config="hw.yaml",
                              arm_robot=True, overrides=["capture.n_views=20"])
    assert trial_overrides(args) == ("backend=real", "robot=my_robot.yaml", "hardware_config=hw.yaml",
                                     "arm_robot=true", "capture.n_views=20")
