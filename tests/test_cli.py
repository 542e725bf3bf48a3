"""The command line as a user meets it: runs, outputs, kill and resume, user data, bad input."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SMALL = [
    "--rounds", "3", "--prompts", "2", "--samples", "3", "--islands", "3",
    "--operating-points", "2", "--skip-ae",
]  # fmt: skip


def jaxdmd(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "jaxdmd.run", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )


@pytest.fixture(scope="module")
def whole_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("whole")
    result = jaxdmd("--out", str(out), *SMALL)
    assert result.returncode == 0, result.stderr[-3000:]
    return out


def test_run_writes_model_plot_and_summary(whole_run):
    summary = json.loads((whole_run / "summary.json").read_text())
    de = summary["de"]
    assert de["rounds"] == 3 and len(de["best_score_history"]) == 4
    assert de["targets"] == ["delta", "omega", "e_qp", "e_dp", "e_dpp"]
    assert set(de["equations"]) == {f"d{t}/dt" for t in de["targets"]}
    assert summary["source"]["benchmark"] == "ieee39-psat-5.1"
    assert (whole_run / "scores.png").stat().st_size > 1000
    model = (whole_run / "model.py").read_text()
    assert "def equation(" in model and "DE_PARAMS" in model
    compile(model, "model.py", "exec")  # the written module is valid Python
    log = (whole_run / "run.log").read_text()  # the progress lines, as the terminal showed them
    assert "DE round  1" in log and "Discovered model" in log and "[bold]" not in log


def test_kill_and_resume_gives_the_same_model(whole_run, tmp_path):
    out = tmp_path / "killed"
    proc = subprocess.Popen(
        [sys.executable, "-m", "jaxdmd.run", "--out", str(out), *SMALL],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    state = out / "de_state.json"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if state.exists() and json.loads(state.read_text())["iteration"] >= 1:
            break
        time.sleep(0.05)
    killed_mid_run = proc.poll() is None
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert killed_mid_run, "the run ended before it could be killed"
    assert not (out / "summary.json").exists()
    resumed = jaxdmd("--resume", str(out))
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    a = json.loads((whole_run / "summary.json").read_text())["de"]
    b = json.loads((out / "summary.json").read_text())["de"]
    assert b["source"] == a["source"]
    assert b["params"] == a["params"]
    assert b["best_score_history"] == a["best_score_history"]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> list[Path]:
    folder = tmp_path_factory.mktemp("recordings")
    base = folder / "gen31.npz"
    result = jaxdmd(
        "simulate", "--fault-bus", "15", "--generator", "31", "--out", str(base),
        "--noise", "0.01", "--operating-points", "2", "--exciter", "--governor",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    files = sorted(folder.glob("gen31*.npz"))
    assert len(files) == 2
    return files


def test_discovery_on_user_data(recordings, tmp_path):
    out = tmp_path / "user"
    result = jaxdmd("--data", *map(str, recordings), "--out", str(out), *SMALL)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["source"]["data"] == [str(p) for p in recordings]


def test_bad_data_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,omega\n0,1\n0,1\n")
    result = jaxdmd("--data", str(bad), "--out", str(tmp_path / "o"), *SMALL)
    assert result.returncode == 2
    assert "error:" in result.stderr and "Traceback" not in result.stderr


def test_closed_llm_port_is_a_clear_error(recordings, tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "JAXDMD_LLM_API_KEY": "sk-test-secret"}
    start = time.monotonic()
    result = subprocess.run(
        [
            sys.executable, "-m", "jaxdmd.run", "--data", *map(str, recordings),
            "--out", str(tmp_path / "llm"), "--llm", f"http://127.0.0.1:{port}/v1",
            "--model", "test-model", "--llm-timeout", "2", *SMALL,
        ],
        capture_output=True, text=True, timeout=300, cwd=ROOT, env=env,
    )  # fmt: skip
    assert result.returncode != 0
    assert f"127.0.0.1:{port}" in result.stderr
    assert "Traceback" not in result.stderr
    assert "sk-test-secret" not in result.stderr + result.stdout
    assert time.monotonic() - start < 240


def test_example_custom_loop_runs():
    result = subprocess.run(
        [sys.executable, "examples/custom_loop.py", "--rounds", "6"],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "library [P_e" in result.stdout  # the hidden variable was brought in
    assert "domega/dt" in result.stdout


@pytest.mark.slow
def test_example_diagnose_runs(tmp_path):
    done = subprocess.run(
        [
            sys.executable,
            "examples/diagnose_your_model.py",
            "--out",
            str(tmp_path),
            "--rounds",
            "3",
        ],
        capture_output=True,
        text=True,
        timeout=900,
        cwd=ROOT,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "cause (missing term)" in done.stdout
    assert (tmp_path / "report" / "report.md").exists()
    assert len(list((tmp_path / "recordings").glob("*.csv.json"))) == 4


def test_rejected_data_leave_no_output_folder(tmp_path):
    """The data are read before anything is written: a rejected --data run creates nothing."""
    bad = tmp_path / "short.csv"
    bad.write_text("t,omega\n0,1\n0.1,1\n")
    out = tmp_path / "never"
    result = jaxdmd("--data", str(bad), "--out", str(out), *SMALL)
    assert result.returncode == 2 and str(bad) in result.stderr
    assert not out.exists()


def test_resume_names_a_corrupt_checkpoint(whole_run, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(whole_run, copy)
    (copy / "de_state.json").write_text('{"archive": ')  # cut off mid-write by hand
    result = jaxdmd("--resume", str(copy))
    assert result.returncode == 2, result.stderr[-2000:]
    assert "de_state.json" in result.stderr and "Traceback" not in result.stderr


# ----------------------------------------------------------------------------------------------
# the command's shape: subcommands, help, the old form (no running)


def test_top_level_help_fits_one_screen():
    result = subprocess.run(
        [sys.executable, "-m", "jaxdmd", "--help"], capture_output=True, text=True, cwd=ROOT
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert len(lines) <= 30, result.stdout
    for command in ("discover", "simulate", "diagnose", "export"):
        assert any(line.split()[:1] == [command] for line in lines), result.stdout


def test_discover_help_shows_user_options_before_the_advanced_ones(capsys):
    from jaxdmd.run import main

    with pytest.raises(SystemExit) as done:
        main(["discover", "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    assert len(text.split("\noptions:")[0].splitlines()) < 12  # a short usage, then the options
    text = text[text.index("\noptions:") :]
    assert text.index("--out") < text.index("--llm-model") < text.index("advanced")
    assert text.index("advanced") < text.index("--islands")
    assert "--model" not in text.replace("--llm-model", "")  # the hidden old spelling


def test_every_option_has_help():
    import argparse

    from jaxdmd.run import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(sub.choices) == {"discover", "simulate", "diagnose", "export"}
    for name, command in sub.choices.items():
        for action in command._actions:
            if action.option_strings and action.help != argparse.SUPPRESS:
                assert action.help, f"{name} {action.option_strings[0]} has no help"


def test_no_subcommand_means_discover_with_the_same_config():
    from jaxdmd.run import config_from_args, parse_args

    old = ["--out", "x", "--rounds", "3", "--islands", "3", "--skip-ae", "--no-weighted"]
    a, b = parse_args(old), parse_args(["discover", *old])
    assert a.command == b.command == "discover"
    assert vars(a) == vars(b)
    assert config_from_args(a) == config_from_args(b)
    assert config_from_args(a).search.n_islands == 3 and not config_from_args(a).algebraic
    default = parse_args([])  # python -m jaxdmd.run: the built-in benchmark
    assert default.command == "discover" and default.data is None and default.out is None
    assert config_from_args(default) == config_from_args(parse_args(["discover"]))


def test_llm_model_and_machine_model_are_different_options():
    from jaxdmd.run import parse_args

    assert parse_args(["--llm-model", "qwen"]).llm_model == "qwen"
    assert parse_args(["discover", "--model", "qwen"]).llm_model == "qwen"  # the old spelling
    sim = parse_args(["simulate", "--out", "a.npz", "--model", "classical"])
    assert sim.model == "classical" and not hasattr(sim, "llm_model")
    diag = parse_args(["diagnose", "--data", "a.npz", "--model", "one-axis"])
    assert diag.model == "one-axis"


def test_progress_lines_go_to_the_log_as_plain_text(tmp_path):
    from jaxdmd.report import Progress
    from jaxdmd.search import RoundReport

    progress = Progress(quiet=True)
    progress.message("Simulating the benchmark...")  # before the folder exists
    log = tmp_path / "run.log"
    progress.log_to(log)
    report = RoundReport(
        round=1, n_samples=16, n_valid=17, dropped=(), best_score=-0.1, improved=True,
        n_recombined=1, done=True, stop_reason="gamma reached",
    )  # fmt: skip
    progress.round("DE", None, report)  # type: ignore[arg-type]
    progress.close()
    text = log.read_text()
    assert "Simulating the benchmark..." in text
    assert "valid 17/17 (dropped 0)" in text  # the recombined candidate is counted in the total
    assert "done: gamma reached" in text and "[bold]" not in text and "\x1b[" not in text
