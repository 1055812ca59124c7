"""The code snippets of the docs run: the RL quick starts of docs/envs.md, the env pages and the README, shortened
(a few steps; the hard grasp-selection variant with a small capture)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHEAP_HARD = 'gym.make("torm/TormGraspSelectHard-v0", n_views=8, capture_scale=0.25, top_k=4, n_points=256)'


def _python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


@pytest.mark.parametrize("doc", ["docs/envs.md", "docs/envs/pick.md", "docs/envs/grasp_select.md", "README.md"])
def test_rl_quick_start_runs(doc):
    path = ROOT / doc
    blocks = [b for b in _python_blocks(path) if "gym.make(" in b]
    assert blocks, f"{doc} has no gym.make snippet"
    code = blocks[0].replace("range(200)", "range(5)").replace('gym.make("torm/TormGraspSelectHard-v0")', CHEAP_HARD)
    scope: dict = {}
    try:
        exec(compile(code, str(path), "exec"), scope)  # noqa: S102 - the docs' own snippet
        obs = scope["obs"]
        if "GraspSelect" in code:
            assert set(obs) == {"candidates", "valid", "object_summary", "object_points"}
            assert scope["info"]["outcome"] and scope["info"]["target_label"] >= 1000  # the step ran
        else:
            assert set(obs) >= {"joint_pos", "tcp_pose"}
    finally:
        if "env" in scope:
            scope["env"].close()
