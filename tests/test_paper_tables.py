"""The paper's two tables (``quasisim bench paper``): its ablations as named methods, the rows' runs and their
seeds, and the tables from measured rows beside the paper's figures."""

from __future__ import annotations

from pathlib import Path

import pytest

from quasisim.bench.paper import ROWS, markdown, measured, runs_of
from quasisim.errors import QuasisimError
from quasisim.method.spec import TransferSpec


def test_the_ablations_are_named_methods_with_the_papers_definitions() -> None:
    """Each ablation is the paper's method (stages 1, 2, 3, mpc, its 8-simulator curriculum, every network of
    stage 3) with one thing taken out, and a conflicting option given with it is refused."""
    full = TransferSpec(method="paper", render=False).checked()
    assert full.stages == ("1", "2", "3", "mpc") and full.curriculum == "default"
    assert full.networks == ("local", "global", "control")
    expect = {
        "paper-no-residual": ("default", ("control",)),
        "paper-no-local-force": ("default", ("global", "control")),
        "paper-no-curriculum": ("none", ("local", "global", "control")),
        "paper-curriculum2": ("curriculum2", ("local", "global", "control")),
    }
    for method, (cur, nets) in expect.items():
        s = TransferSpec(method=method, render=False).checked()
        assert (s.stages, s.curriculum, s.networks) == (full.stages, cur, nets), method
        assert s.identity()["networks"] == nets and s.checked() == s  # checking twice changes nothing
    with pytest.raises(QuasisimError, match="curriculum 'none' of its own"):
        TransferSpec(method="paper-no-curriculum", curriculum="lean").checked()
    with pytest.raises(QuasisimError, match="networks"):
        TransferSpec(method="paper-no-residual", networks=("global", "control")).checked()


def test_the_tables_runs_and_the_ablations_seeded_by_the_full_method() -> None:
    """The tables run ``paper`` first; the ablations with its curriculum start from its checkpoints, the
    others (another curriculum, another method) from nothing; a curriculum's ``+`` runs keep their seeds."""
    from quasisim.bench.transfer import jobs, run_spec

    runs = runs_of(("main", "ablation"))
    assert runs[0] == "paper" and set(runs) == {r.run for r in ROWS if r.run} | {"cascade"}
    specs = {r: run_spec(r, ("1", "2"), TransferSpec(render=False)) for r in (*runs, "short", "short+sample")}
    seeds = {r.name: r.seed_from for r in jobs([Path("clip.npz")], specs)[0].runs}
    assert seeds["paper-no-residual"] == seeds["paper-no-local-force"] == "paper"
    assert seeds["paper-no-curriculum"] is seeds["paper-curriculum2"] is seeds["paper"] is None
    assert seeds["paper-no-analytical"] is None  # no curriculum to share
    assert seeds["mpc-base"] is seeds["cascade"] is None and seeds["short+sample"] == "short"


def test_an_unknown_table_is_refused_with_the_valid_ones() -> None:
    from quasisim.bench.paper import run_paper_bench

    with pytest.raises(QuasisimError, match="valid tables: main, ablation"):
        run_paper_bench(Path("."), (), "*.npz", ("mian",), Path("unused"), None, True, None, 0)


def _metrics(r: float, strict: bool, robust: float | None) -> dict:
    success = {"10deg_10cm": strict, "15deg_15cm": True, "20deg_20cm": True, "strict": strict}
    m = {"R_err_deg": r, "T_err_cm": r / 10, "MPJPE_mm": 2 * r, "CD_mm": r / 2, "success": success}
    return m | ({"robust": {"strict": robust}} if robust is not None else {})


def test_the_tables_hold_our_means_beside_the_papers_figures() -> None:
    """Means and success rates over the clips a row has (a row with fewer says so), the paper's figures
    beside them, and the rows quasisim has no method for say so."""
    clips = ["a", "b"]
    paper = measured({"a": _metrics(10.0, True, 1.0), "b": _metrics(20.0, False, 0.5)}, clips)
    assert paper is not None and paper["R_err_deg"] == 15.0 and paper["strict"] == 50.0
    assert paper["robust_open"] == 75.0 and paper["robust_closed"] is None
    partial = measured({"a": _metrics(4.0, True, None)}, clips)
    text = "\n".join(
        markdown({"paper": paper, "paper-no-residual": partial, "mpc-base": None}, ("main", "ablation"), 2)
    )
    lines = {ln.split(" | ")[0]: ln for ln in text.splitlines() if ln.startswith("| ")}
    assert (
        "| 2 | 15.0 | 1.50 | 30.0 | 7.5 | 50/100/100 | 50 | 75 | - | 24.2 / 1.97 / 24.4 / 9.8 / 27/37/59 |"
        in lines["| Ours"]
    )
    assert "| 1 of 2 | 4.0 |" in lines["| Ours w/o Residual Physics"]
    row = "| DGrasp-Tracking (w/ curric.)"
    assert "policy `dgrasp-tracking-curriculum` | - |" in lines[row] and "| 33.9 / 4.60 /" in lines[row]
    assert all(r.run or r.policy for r in ROWS)  # every row of the paper's tables is built
    assert lines["| MPC (w/ base sim.)"].count("| - ") >= 9  # asked for, nothing measured yet
    for table in text.split("#### ")[1:]:  # every row has as many cells as the header
        rows = [ln for ln in table.splitlines() if ln.startswith("|")]
        assert len({ln.count("|") for ln in rows}) == 1, table


def test_runs_of_other_folders_fill_the_rows_out_lacks(tmp_path, monkeypatch) -> None:
    """``--from``: a clip's run missing in OUT is read from the first other folder that has it; OUT's own run of a
    clip stands where both have one; the other folders are only read (report only)."""
    import json

    import quasisim.bench.transfer as bt
    from quasisim.bench.paper import run_paper_bench

    clips = [tmp_path / f"c{i}.npz" for i in range(2)]
    monkeypatch.setattr("quasisim.eval.tables.clips", lambda data, pattern, names: clips)

    def row(clip: str, method: str, r: float) -> dict:
        return {"clip": clip, "method": method, **_metrics(r, True, 0.5)}

    def in_out(data, names, pattern, runs, stages, budget, target, hand, out, report_only, *rest):
        (out / "transfer.json").write_text(json.dumps([row("c0", "paper", 10.0)]))

    calls = []

    def in_source(data, names, pattern, runs, stages, budget, target, hand, folder, report_only, *rest):
        calls.append((folder.name, report_only))
        r = {"a": 20.0, "b": 40.0}[folder.name]
        return [row("c0", "paper", r), row("c1", "paper", r), row("c1", "mpc-base", r)]

    monkeypatch.setattr(bt, "run_transfer_bench", in_out)
    monkeypatch.setattr(bt, "transfer_rows", in_source)
    out = tmp_path / "out"
    out.mkdir()
    text = run_paper_bench(
        tmp_path, (), "*.npz", ("main",), out, None, True, None, 0, "fast", (tmp_path / "a", tmp_path / "b")
    )
    assert calls == [("a", True), ("b", True)]
    lines = {ln.split(" | ")[0]: ln for ln in text.splitlines() if ln.startswith("| ")}
    assert "| 2 | 15.0 |" in lines["| Ours"]  # c0 from OUT (10), c1 from the first folder (20), not the second's
    assert "| 1 of 2 | 20.0 |" in lines["| MPC (w/ base sim.)"]
