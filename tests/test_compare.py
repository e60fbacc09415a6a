"""compare: a subdirectory per --by, every line labelled with its case, legends in numeric order, diverged cases
marked as diverged (never plotted at the figures of a run that stopped)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")

from matplotlib.figure import Figure

from implicit_cloth.cli import main


@pytest.fixture
def sweep_dir(tmp_path):
    """A hand-made summary: dt x stiffness x integrator; one case diverged before its first kept frame."""
    cases = []
    for integ in ("backward_euler", "bdf2"):
        for k in (1000.0, 20000.0, 5000.0):
            for dt in (0.01, 0.02):
                diverged = integ == "bdf2" and k == 20000.0 and dt == 0.02
                cases.append({"case_id": f"{integ}-{k}-{dt}", "simulation.dt": dt, "simulation.integrator": integ,
                              "cloth.springs.structural.stiffness": k,
                              "status": "diverged" if diverged else "ok", "reason": "",
                              "wall_s": 0.0 if diverged else 1.0 + dt, "energy_drift_rel": 0.0 if diverged else k * dt,
                              "max_strain": 0.0 if diverged else 0.01, "mean_iterations": None})
    out = tmp_path / "sweep"
    out.mkdir()
    keys = ["simulation.dt", "simulation.integrator", "cloth.springs.structural.stiffness"]
    counts = {"ok": 11, "diverged": 1, "failed": 0, "pending": 0}
    (out / "summary.json").write_text(json.dumps({"sweep": "sweep.toml", "base": "base.toml", "keys": keys,
                                                  "columns": list(cases[0]), "counts": counts, "cases": cases}))
    return out


def _capture(monkeypatch):
    figs = []
    real = Figure.savefig

    def savefig(self, *a, **k):
        figs.append(self)
        return real(self, *a, **k)
    monkeypatch.setattr(Figure, "savefig", savefig)
    return figs


def test_compare_writes_one_folder_per_by_and_labels_every_line(sweep_dir, monkeypatch, capsys):
    figs = _capture(monkeypatch)
    assert main(["compare", str(sweep_dir), "--by", "simulation.integrator", "--metrics", "energy_drift_rel"]) == 0
    assert main(["compare", str(sweep_dir), "--by", "cloth.springs.structural.stiffness",
                 "--metrics", "energy_drift_rel"]) == 0
    assert main(["compare", str(sweep_dir), "--metrics", "energy_drift_rel"]) == 0
    files = capsys.readouterr().out.split()
    rel = sorted(str(p.relative_to(sweep_dir)) for p in (sweep_dir / "compare").rglob("*.png"))
    assert rel == ["compare/by_cloth_springs_structural_stiffness/energy_drift_rel_vs_simulation_dt.png",
                   "compare/by_simulation_integrator/energy_drift_rel_vs_simulation_dt.png",
                   "compare/per_case/energy_drift_rel_vs_simulation_dt.png"]
    assert len(files) == 3
    by_integ, by_k, per_case = ([t.get_text() for t in f.axes[0].get_legend().get_texts()] for f in figs)
    # by integrator: six lines (one per case combination), each labelled with it, stiffness in numeric order
    assert by_integ[:6] == [f"integrator={i}, stiffness={k}"
                            for i in ("backward_euler", "bdf2") for k in ("1000", "5000", "20000")]
    assert by_k[:6] == [f"stiffness={k}, integrator={i}" for k in ("1000", "5000", "20000")
                        for i in ("backward_euler", "bdf2")]
    assert len(set(by_integ)) == len(by_integ) and len(set(per_case)) == len(per_case)
    assert by_integ[-1] == "diverged (no value; marked at the top)"


def test_a_diverged_case_is_marked_not_plotted_at_zero(sweep_dir, monkeypatch):
    figs = _capture(monkeypatch)
    assert main(["compare", str(sweep_dir), "--by", "simulation.integrator", "--metrics", "energy_drift_rel"]) == 0
    ax = figs[0].axes[0]
    lines = [ln for ln in ax.get_lines() if len(ln.get_xdata())]
    crosses = [ln for ln in lines if ln.get_marker() == "x"]
    assert len(crosses) == 1 and list(crosses[0].get_xdata()) == [0.02]
    assert list(crosses[0].get_ydata()) == [1.0]                       # axes fraction: the top edge
    data = [ln for ln in lines if ln.get_marker() != "x"]
    assert all(0.0 not in list(ln.get_ydata()) for ln in data)         # the diverged 0 is never a value
    bdf2_20000 = [ln for ln in data if ln.get_label() == "integrator=bdf2, stiffness=20000"]
    assert len(bdf2_20000) == 1 and list(bdf2_20000[0].get_xdata()) == [0.01]


def test_compare_help_names_the_files_compare_writes(sweep_dir, capsys):
    """The paths in ``compare --help`` are those written, with and without --by."""
    assert main(["compare", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    patterns = re.findall(r"DIR/compare/[\w<>/]+\.png", text)
    assert patterns == ["DIR/compare/per_case/<metric>_vs_<key>.png", "DIR/compare/by_<KEY>/<metric>_vs_<key>.png"]
    assert "by_simulation_integrator/max_strain_vs_simulation_dt.png" in text
    for pattern, by in zip(patterns, (None, "simulation.integrator")):
        assert main(["compare", str(sweep_dir), "--metrics", "max_strain"] + (["--by", by] if by else [])) == 0
        written = capsys.readouterr().out.split()
        want = (pattern.replace("DIR", str(sweep_dir)).replace("<metric>", "max_strain")
                .replace("<key>", "simulation_dt").replace("<KEY>", (by or "").replace(".", "_")))
        assert written == [want]
        assert Path(want).is_file()

