"""Benchmarks' quick (CI smoke) mode writes well-formed outputs. Numbers are not asserted."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_step_cost_quick(tmp_path):
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "step_cost.py"), "--quick", "--out", str(tmp_path)],
                   check=True, capture_output=True, text=True)
    res = json.loads((tmp_path / "step_cost.json").read_text())
    assert res["benchmark"] == "step_cost" and res["quick"] is True
    assert [r["resolution"] for r in res["rows"]] == [8, 16]
    for r in res["rows"]:
        assert r["ms_step"] > 0 and r["iterations_median"] >= 1 and r["step_in_spmvs"] > 0
    md = (tmp_path / "step_cost.md").read_text()
    assert md.count("\n| 8² |") + md.count("\n| 16² |") == 2
