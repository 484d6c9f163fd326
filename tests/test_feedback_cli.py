"""``icefab tune`` end to end."""
from __future__ import annotations

import json

import pytest

from icefab.cli import main


def run(capsys, *argv):
    rc = main(["tune", *argv])
    out, err = capsys.readouterr()
    return rc, out, err


def test_tune_json_thesis_disturbance(capsys):
    rc, out, _ = run(capsys, "--layers", "100", "--pulse", "0.5@60", "--step", "0.2@30",
                     "--json")
    assert rc == 0
    data = json.loads(out)
    assert set(data) == {"kp", "ki", "kd", "rms", "max_pole", "stable", "optimised",
                         "converged", "converged_by_check"}
    assert data["optimised"] is True
    assert data["converged"] is True and data["converged_by_check"] is False
    assert data["kp"] == pytest.approx(1.0, abs=2e-3) and abs(data["kd"]) < 2e-3
    assert data["ki"] == pytest.approx(0.33, abs=5e-3)
    assert data["rms"] == pytest.approx(0.061, abs=5e-4) and data["stable"] is True


def test_tune_evaluate_unstable(capsys):
    rc, out, _ = run(capsys, "--gains", "1,0.33,0.45", "--json")
    data = json.loads(out)
    assert rc == 0 and data["stable"] is False and data["max_pole"] == pytest.approx(1.05, abs=0.005)
    rc, out, _ = run(capsys, "--gains", "1,0.33,0.45")
    assert "UNSTABLE" in out and "1.048" in out


def test_given_gains_are_not_said_to_have_converged(capsys, tmp_path):
    """'--gains ... --json' said "converged": true, though no optimiser ran (a review's):
    the same keys, optimised false and converged null, in tune.json too, and the text
    says the gains were given."""
    rc, out, _ = run(capsys, "--gains", "0.5,0.3,0.1", "--json", "-o", str(tmp_path / "t"))
    data = json.loads(out)
    assert rc == 0 and data["optimised"] is False
    assert data["converged"] is None and data["converged_by_check"] is None
    saved = json.loads((tmp_path / "t" / "tune.json").read_text())
    assert saved["mode"] == "given, not optimised" and saved["optimised"] is False
    assert saved["converged"] is None
    rc, out, _ = run(capsys, "--gains", "0.5,0.3,0.1")
    assert rc == 0 and out.startswith("gains (given, not optimised): Kp = 0.5000")
    assert "converged" not in out


def test_tune_says_when_the_optimiser_failed(capsys):
    """From a divergent start the unconstrained optimiser stops at once (scipy: "NaN
    result encountered"): the gains were printed as "optimised" (hunt P)."""
    rc, out, err = run(capsys, "--unconstrained", "--start", "100,100,100")
    assert rc == 1 and "did not converge" in err
    assert out.startswith("gains (not optimised: the optimiser stopped after 0 iterations, ")
    assert "try another --start" in out.splitlines()[0]
    rc, out, _ = run(capsys, "--unconstrained", "--start", "100,100,100", "--json")
    assert rc == 1 and json.loads(out)["converged"] is False


def test_tune_writes_nothing_when_the_optimiser_failed(tmp_path, capsys):
    """Gains the optimiser did not reach are no result: exit status 1 and no folder, as
    for any command that fails, so that a script does not take them for the optimum."""
    out_dir = tmp_path / "t"
    rc, _, err = run(capsys, "--unconstrained", "--start", "100,100,100", "-o", str(out_dir))
    assert rc == 1 and f"nothing written to {out_dir}" in err
    assert not out_dir.exists() and list(tmp_path.iterdir()) == []
    rc, _, _ = run(capsys, "--gains", "100,100,100", "-o", str(out_dir))
    assert rc == 0 and (out_dir / "tune.json").is_file()   # evaluated gains are a result


def test_tune_fix_kp_ki_optimises_kd(capsys):
    rc, out, _ = run(capsys, "--fix-kp", "1", "--fix-ki", "0.33", "--pulse", "0@60",
                     "--step", "0.2@30", "--json")
    data = json.loads(out)
    assert (data["kp"], data["ki"]) == (1.0, 0.33)
    assert data["kd"] == pytest.approx(0.126, abs=2e-3)  # thesis Table 5-3


def test_tune_writes_plot(tmp_path, capsys):
    out_dir = tmp_path / "t"
    rc, out, _ = run(capsys, "--noise", "0.05", "-o", str(out_dir))
    assert rc == 0 and "stable" in out
    png = (out_dir / "error_response.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((out_dir / "tune.json").read_text())["noise"] == 0.05


@pytest.mark.parametrize("argv,msg", [
    (["--pulse", "0.5"], "AMPLITUDE@LAYER"),
    (["--pulse", "0.5@600"], "1..100"),
    (["--step", "a@3"], "amplitude"),
    (["--layers", "0"], ">= 1"),
    (["--gains", "1,2"], "three numbers"),
    (["--gains", "1,nan,0"], "finite"),
    (["--noise", "-1"], ">= 0"),
    (["--gains", "1,0.3,0", "--fix-kp"], "cannot be combined"),
    (["--fix-kp", "3"], "gain-stable volume"),
])
def test_tune_bad_arguments_exit_2(tmp_path, capsys, argv, msg):
    rc, out, err = run(capsys, *argv, "-o", str(tmp_path / "x"))
    assert rc == 2 and out == ""
    assert msg in err and err.count("\n") == 1
    assert not (tmp_path / "x").exists()



def test_tune_plot_of_diverging_gains_stays_readable(tmp_path, capsys, monkeypatch):
    """Unstable gains: the plot keeps the disturbance's scale and says the error diverges
    (a linear axis up to 1e150 showed nothing); the summary gives no RMS for it."""
    import matplotlib.figure

    from icefab import Job
    from icefab.feedback import Disturbance, evaluate_gains
    from icefab.report import plot_error_response

    out = tmp_path / "t"
    assert main(["tune", "--gains", "3,3,3", "--layers", "200", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "UNSTABLE" in text and "diverges" in text and "e+" not in text
    assert max(map(len, text.splitlines())) < 120
    assert (out / "error_response.png").stat().st_size > 10_000

    seen = {}
    real_save = matplotlib.figure.Figure.savefig

    def keep(fig, *a, **k):
        seen["ylim"] = fig.axes[0].get_ylim()
        seen["text"] = [t.get_text() for t in fig.axes[0].texts]
        return real_save(fig, *a, **k)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    dist = Disturbance(n_layers=200)
    plot_error_response(evaluate_gains((3, 3, 3), dist), dist, Job(), tmp_path / "p.png",
                        "evaluated")
    assert max(abs(v) for v in seen["ylim"]) <= 20
    assert any(t.startswith("diverges: |e| > 7 from layer") for t in seen["text"])
    plot_error_response(evaluate_gains((1, 0.33, 0), dist), dist, Job(), tmp_path / "q.png",
                        "evaluated")
    assert seen["text"] == []


def test_tune_refuses_what_it_used_to_tune_against_nothing(capsys, tmp_path):
    # --layers under 60 dropped the thesis' pulse (and under 30 its step) and "optimised"
    # against no disturbance; an explicit zero disturbance too; every gain held
    rc, _, err = run(capsys, "--layers", "20")
    assert rc == 2 and "--layers 20: the thesis' disturbance has its pulse at layer 60" in err
    rc, _, err = run(capsys, "--noise", "0")
    assert rc == 2 and "the disturbance is 0 at every layer" in err
    rc, _, err = run(capsys, "--step", "0@10")
    assert rc == 2 and "the disturbance is 0 at every layer" in err
    rc, _, err = run(capsys, "--fix-kp", "0", "--fix-ki", "0", "--fix-kd", "0")
    assert rc == 2 and "hold every gain: nothing to optimise" in err
    # tune.json records the disturbance used, the thesis' when none is given
    rc, _, _ = run(capsys, "-o", str(tmp_path / "t"))
    assert rc == 0
    data = json.loads((tmp_path / "t" / "tune.json").read_text())
    assert (data["format"], data["version"]) == ("icefab-tune", 1)
    assert (data["pulses"], data["steps"], data["noise"]) == ([[0.5, 60]], [[0.2, 30]], 0.0)
    # a large disturbance: the same optimum (the model is linear)
    rc, out, _ = run(capsys, "--pulse", "1e6@60", "--json")
    big = json.loads(out)
    rc, out, _ = run(capsys, "--pulse", "1@60", "--json")
    unit = json.loads(out)
    assert rc == 0 and big["kp"] == pytest.approx(unit["kp"], abs=1e-5)
    assert big["rms"] == pytest.approx(unit["rms"] * 1e6, rel=1e-6)
