"""Bad command-line values are one line on stderr and exit 2 (no usage text)."""

from __future__ import annotations

import pytest

from implicit_cloth.cli import main

H = "(see implicit-cloth {} --help)"


@pytest.mark.parametrize("argv, line", [
    (["run", "s.toml", "--dt", "abc"],
     "implicit-cloth: error: --dt: invalid float value: 'abc'" + " " + H.format("run")),
    (["run"],
     "implicit-cloth: error: the following arguments are required: SCENE.toml" + " " + H.format("run")),
    (["export", "d", "--frames", "1", "x"],
     "implicit-cloth: error: --frames: invalid int value: 'x'" + " " + H.format("export")),
    (["render", "d", "--size", "640"],
     "implicit-cloth: error: --size: expected 2 arguments" + " " + H.format("render")),
    (["batch", "s.toml", "--workers", "two"],
     "implicit-cloth: error: --workers: invalid int value: 'two'" + " " + H.format("batch")),
    (["simulate"], "implicit-cloth: error: COMMAND: invalid choice: 'simulate' (choose from 'run', 'bench', 'batch', "
                   "'export', 'render', 'compare') (see implicit-cloth --help)"),
    (["run", "s.toml", "--speed", "2"],
     "implicit-cloth: error: unrecognized arguments: --speed 2 (see implicit-cloth --help)"),
])
def test_bad_command_line_values_are_one_line(argv, line, capsys):
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [line] and captured.out == ""
