"""The README's two commands are what a fresh machine runs; CI runs the second one verbatim."""

from __future__ import annotations

import re

from conftest import REPO_ROOT


def _readme_commands() -> list[str]:
    text = (REPO_ROOT / "README.md").read_text()
    blocks = re.findall(r"```(?:bash|sh)\n(.*?)```", text, flags=re.S)
    return [b.strip() for b in blocks[:2]]


def test_readme_starts_with_two_commands_and_ci_runs_the_second():
    train_cmd, test_cmd = _readme_commands()
    assert "python train.py model=superlite" in train_cmd
    assert "torch==2.13.0" in train_cmd and "torch==2.13.0" in test_cmd  # the CPU wheel, not a CUDA download
    ci = (REPO_ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    assert ci == test_cmd
