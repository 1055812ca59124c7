"""Benchmark grid, seeds and config validation (torm.bench.spec)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from torm.bench.spec import (
    BenchConfig,
    build_grid,
    config_hash,
    load_trial_fn,
    parse_list,
    trial_key,
    trial_seed,
)
from torm.errors import ConfigError, UnknownNameError


def test_trial_seed_is_stable_across_processes_and_in_range():
    seeds = [trial_seed("rw", f"rw{i}", t) for i in range(1, 4) for t in range(5)]
    code = ("from torm.bench.spec import trial_seed; "
            "print([trial_seed('rw', f'rw{i}', t) for i in range(1, 4) for t in range(5)])")
    # a different PYTHONHASHSEED would change hash(): the seed must not depend on it
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONHASHSEED": "12345"}).stdout
    assert eval(out) == seeds
    assert all(0 <= s < 2**31 for s in seeds)
    assert len(set(seeds)) == len(seeds)  # distinct trials get distinct layouts
    # documented formula: first 4 bytes of sha256("base/suite/scenario/trial"), 31 bits
    import hashlib

    assert trial_seed("rw", "rw1", 0) == int.from_bytes(hashlib.sha256(b"0/rw/rw1/0").digest()[:4], "big") & 0x7FFFFFFF
    assert trial_seed("rw", "rw1", 0, base_seed=1) != trial_seed("rw", "rw1", 0)


def test_grid_is_trial_major_and_methods_share_seeds():
    cfg = BenchConfig(suite="rw", scenarios=("rw1", "rw3"), trials=2, methods=("torm", "depth"))
    grid = build_grid(cfg)
    assert [s.key for s in grid] == [
        "rw/rw1/0/torm", "rw/rw1/0/depth", "rw/rw3/0/torm", "rw/rw3/0/depth",
        "rw/rw1/1/torm", "rw/rw1/1/depth", "rw/rw3/1/torm", "rw/rw3/1/depth"]
    by = {s.key: s for s in grid}
    assert by["rw/rw1/0/torm"].seed == by["rw/rw1/0/depth"].seed == trial_seed("rw", "rw1", 0)
    assert by["rw/rw1/0/torm"].seed != by["rw/rw1/1/torm"].seed
    assert by["rw/rw3/0/torm"].objects == ("cylinder", "hexagonal_prism")
    assert trial_key("rw", "rw3", 1, "depth") == "rw/rw3/1/depth"
    full = build_grid(BenchConfig(suite="rw"))
    assert [s.scenario for s in full] == [f"rw{i}" for i in range(1, 9)]


def test_unknown_names_list_valid_choices():
    with pytest.raises(UnknownNameError, match="valid choices: lab, rw, syn, syn_hard"):
        build_grid(BenchConfig(suite="nope"))
    with pytest.raises(UnknownNameError, match="depth, depth_fusion, oracle, package.module:callable, torm"):
        BenchConfig(methods=("torm", "lidar"))
    with pytest.raises(UnknownNameError, match="rw1"):
        build_grid(BenchConfig(suite="rw", scenarios=("syn1",)))
    with pytest.raises(UnknownNameError, match="failures"):
        BenchConfig(record="some")


def test_config_validation():
    with pytest.raises(ConfigError, match="trials"):
        BenchConfig(trials=0)
    with pytest.raises(ConfigError, match="workers"):
        BenchConfig(workers=0)
    with pytest.raises(ConfigError, match="timeout"):
        BenchConfig(timeout_s=0)
    with pytest.raises(ConfigError, match="set per trial"):
        BenchConfig(overrides=("seed=3",))
    with pytest.raises(ConfigError, match="section.key=value"):
        BenchConfig(overrides=("capture.n_views",))
    with pytest.raises(ConfigError, match="twice"):
        BenchConfig(methods=("torm", "torm"))
    BenchConfig(overrides=("capture.seed=3",))  # nested keys named like grid keys are fine


def test_config_hash_covers_identity_only_and_roundtrips():
    a = BenchConfig(suite="rw", trials=2, workers=1)
    assert config_hash(a) == config_hash(BenchConfig(suite="rw", trials=5, workers=4, engine="ray"))
    assert config_hash(a) != config_hash(BenchConfig(suite="rw", overrides=("capture.n_views=4",)))
    assert config_hash(a) != config_hash(BenchConfig(suite="rw", timeout_s=10))
    assert config_hash(a) != config_hash(BenchConfig(suite="syn"))
    assert BenchConfig.from_dict(a.as_dict()) == a
    with pytest.raises(ConfigError, match="unknown key"):
        BenchConfig.from_dict({"suite": "rw", "trails": 3})


def test_load_trial_fn_and_parse_list():
    assert callable(load_trial_fn("torm.bench.trial:run_spec"))
    with pytest.raises(ConfigError, match="no function"):
        load_trial_fn("torm.bench.trial:nope")
    with pytest.raises(ConfigError, match="cannot import"):
        load_trial_fn("torm.no_such_module:run")
    assert parse_list(["torm,depth", "oracle"]) == ("torm", "depth", "oracle")
