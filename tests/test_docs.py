"""The documentation's examples work as written.

Every ```python block of README.md and docs/*.md runs, in a fresh interpreter, in a temporary directory that
holds a copy of examples/ (blocks use paths such as ``examples/hanging.toml``); a block that should not run
uses another fence language (```text, ```toml, ...). The README's ```sh commands name subcommands, options,
files and benchmarks that exist, and the relative links of README.md and docs/*.md point at files that exist.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from implicit_cloth.cli import build_parser

if sys.version_info >= (3, 11):
    import tomllib
else:                                                  # pragma: no cover - Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]

FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```\s*$", re.MULTILINE | re.DOTALL)


def blocks(path: Path, language: str) -> list[tuple[int, str]]:
    """(line number, code) of every fenced block of ``language`` in the Markdown file ``path``."""
    text = path.read_text(encoding="utf-8")
    found = []
    for m in FENCE.finditer(text):
        if m.group(1).strip() == language:
            found.append((text.count("\n", 0, m.start()) + 1, m.group(2)))
    return found


PYTHON_BLOCKS = [
    pytest.param(code, id=f"{path.relative_to(ROOT)}:{line}")
    for path in PAGES for line, code in blocks(path, "python")
]


def test_the_readme_is_a_guide_not_a_record():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 300
    assert not re.findall(r"\b20\d\d-\d\d-\d\d\b|\bissue \d+", text), "dates and issue numbers belong in git"


def test_the_readme_has_python_examples():
    assert len(blocks(README, "python")) >= 2, "the README's Python API examples are ```python blocks"


@pytest.mark.parametrize("code", PYTHON_BLOCKS)
def test_python_block_runs(code, tmp_path):
    shutil.copytree(ROOT / "examples", tmp_path / "examples")
    script = tmp_path / "block.py"
    script.write_text(code, encoding="utf-8")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, f"the block failed:\n{code}\n--- stderr:\n{proc.stderr[-4000:]}"


# --------------------------------------------------------------------------- the README's shell commands
def commands(code: str) -> list[list[str]]:
    """The commands of a sh block: continuation lines joined, comments dropped, split at ``&&``."""
    found = []
    for line in code.replace("\\\n", " ").splitlines():
        words = shlex.split(line, comments=True)
        while words:
            cut = words.index("&&") if "&&" in words else len(words)
            found.append(words[:cut])
            words = words[cut + 1:]
    return found


README_COMMANDS = [cmd for _, code in blocks(README, "sh") for cmd in commands(code)]
SUBCOMMANDS = {"run", "batch", "export", "render", "compare", "bench"}


def test_the_readme_shows_its_commands():
    programs = {cmd[0] for cmd in README_COMMANDS}
    assert {"pip", "implicit-cloth", "pytest"} <= programs, programs


@pytest.mark.parametrize("cmd", README_COMMANDS, ids=lambda cmd: " ".join(cmd)[:60])
def test_readme_command_names_what_exists(cmd):
    program, args = cmd[0], cmd[1:]
    if program == "implicit-cloth":
        assert args and args[0] in SUBCOMMANDS, cmd
        if args[0] == "bench":                       # the benchmark's own parser answers --help
            proc = subprocess.run([sys.executable, "-m", "implicit_cloth", "bench", args[1], "--help"], cwd=ROOT,
                                  capture_output=True, text=True, timeout=300)
            assert proc.returncode == 0, f"bench {args[1]} --help: {proc.stderr[-2000:]}"
        else:
            build_parser().parse_args(args)          # exits with code 2 on an unknown option or bad value
        for arg in args[1:]:
            if arg.endswith(".toml"):
                assert (ROOT / arg).is_file(), f"{arg} does not exist"
    elif program == "python":
        assert (ROOT / args[0]).is_file(), f"{args[0]} does not exist"
    elif program == "pip":
        assert args[:2] == ["install", "-e"], cmd
        extras = re.fullmatch(r"\.(?:\[([a-z,]+)\])?", args[2])
        assert extras, args[2]
        optional = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
        for extra in filter(None, (extras.group(1) or "").split(",")):
            assert extra in optional, f"no extra {extra!r} in pyproject.toml"
    elif program == "pytest":
        pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
        if "-n" in args:
            assert any(dep.startswith("pytest-xdist") for dep in pyproject["project"]["optional-dependencies"]["test"])
        if "-m" in args:
            marker = args[args.index("-m") + 1].split()[-1]
            assert any(m.startswith(f"{marker}:") for m in pyproject["tool"]["pytest"]["ini_options"]["markers"])
    else:
        pytest.fail(f"the README runs {program!r}, which this test does not check")


# --------------------------------------------------------------------------- links
LINK = re.compile(r"\]\(([^)\s]+)\)")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_exist(page):
    missing = []
    for target in LINK.findall(page.read_text(encoding="utf-8")):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue                                       # a web address or an anchor of the page itself
        if not (page.parent / target.split("#")[0]).exists():
            missing.append(target)
    assert not missing, f"{page.name} links to files that do not exist: {missing}"
