import json

from typer.testing import CliRunner

from cutterpose.cli import app

runner = CliRunner()


def test_experiment_synthetic_cli(tmp_path):
    out = tmp_path / "syn"
    r = runner.invoke(app, ["experiment", "synthetic", "--methods", "opencv-ippe-lm",
                            "--trials", "20", "--sigmas", "0,1", "--out", str(out),
                            "--no-progress"])
    assert r.exit_code == 0, r.output
    for f in ("trials.csv", "summary.md", "summary.json", "fig5.png"):
        assert (out / f).is_file()
    s = json.loads((out / "summary.json").read_text())
    assert [st["sigma_px"] for st in s["stats"]] == [0.0, 1.0]
    assert s["stats"][0]["failed"] == 0


def test_unknown_method_is_a_clean_error(tmp_path):
    r = runner.invoke(app, ["experiment", "synthetic", "--methods", "nope", "--trials", "2",
                            "--out", str(tmp_path)])
    assert r.exit_code == 2
    assert "unknown method 'nope'" in r.output
    assert "Traceback" not in r.output


def test_bad_sigmas_is_a_clean_error(tmp_path):
    r = runner.invoke(app, ["experiment", "synthetic", "--sigmas", "1:0", "--trials", "2",
                            "--out", str(tmp_path)])
    assert r.exit_code == 2 and "sigmas" in r.output


def test_methods_listing():
    r = runner.invoke(app, ["methods"])
    assert r.exit_code == 0 and "opencv-ippe-lm" in r.output and "dm+" in r.output
