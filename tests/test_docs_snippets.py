"""The code snippets of the docs run: the RL quick start of docs/envs.md (and the README), shortened to a few steps."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def test_rl_quick_start_runs():
    for doc in (ROOT / "docs" / "envs.md", ROOT / "README.md"):
        blocks = [b for b in _python_blocks(doc) if "gym.make(" in b]
        assert blocks, f"{doc.name} has no gym.make snippet"
        code = blocks[0].replace("range(200)", "range(5)")
        scope: dict = {}
        exec(compile(code, str(doc), "exec"), scope)  # noqa: S102 - the docs' own snippet
        assert set(scope["obs"]) >= {"joint_pos", "tcp_pose", "object_pos"}
