"""``fieldlog study``: the command names match the module, and the cost study measures every method."""

import polars as pl

from fieldlog.tools.evaluation import studies
from fieldlog.tools.cli import build_parser, main


def test_study_choices_match_the_module():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    names = next(a for a in sub.choices["study"]._actions if a.dest == "name").choices
    assert tuple(names) == studies.STUDIES


def test_cost_study_reports_every_method_and_the_paper_flops(tmp_path):
    assert main(["study", "cost", "--runs", "1", "--out", str(tmp_path / "cost")]) == 0
    table = pl.read_csv(tmp_path / "cost" / "table.csv")
    assert set(table["method"]) == {"kf", "kf-ukf", "sckf", "ssr-sckf", "hinf"}
    assert (table["value"] > 0).all()
    assert len(table) == 10  # predict and total per method
    report = (tmp_path / "cost" / "report.md").read_text()
    assert "13710" in report and "25245" in report and "30801" in report and "42336" in report  # the paper's Table 4
    assert studies.flops_kf(15, 6) == (13710, 30801)
    assert round(studies.flops_ukf(15, 6)[0]) == 25245 and round(studies.flops_ukf(15, 6)[1]) == 42336
