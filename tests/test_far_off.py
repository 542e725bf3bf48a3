"""The ``far_off`` flag: rollouts that stay bounded but are far off (R^2 < -10), next to
``diverged`` (issue #15, item 4a)."""

from __future__ import annotations

import numpy as np
from benchmark_scripts import load_script

import jaxdmd  # noqa: F401  (float64)
from jaxdmd.data import Dataset
from jaxdmd.report import rollout_summary, rollout_table
from jaxdmd.rollout import FAR_OFF_R2, score

T = np.round(np.arange(0.0, 3.0, 0.01), 10)
X = np.sin(2 * np.pi * T)
Y = np.cos(2 * np.pi * T)
DS = Dataset.create(T, {"x": X, "y": Y}, {"x": "state", "y": "state"}, events=(1.0,))


def test_a_bounded_but_far_off_rollout_is_flagged():
    good = score({"x": X + 0.01, "y": Y}, DS)
    assert good["far_off"] is False and good["far_off_states"] == []
    far = score({"x": X + 5.0, "y": Y}, DS)  # bounded, R^2 = 1 - 25 / 0.5 = -49
    assert far["full"]["per_state"]["x"]["r2"] < FAR_OFF_R2
    assert far["far_off"] is True and far["far_off_states"] == ["x"]
    assert "diverged" not in far  # not a RolloutResult: the old flag is left as it was
    nan = score({"x": np.full_like(X, np.nan), "y": Y}, DS)  # non-finite: R^2 = -inf
    assert nan["far_off"] is True and nan["far_off_states"] == ["x"]


def test_summary_and_terminal_table_show_far_off_rollouts():
    scores = [score({"x": X + 5.0, "y": Y}, DS), score({"x": X, "y": Y + 0.01}, DS)]
    summary = rollout_summary(scores)
    assert summary["n_far_off"] == 1 and summary["far_off_states"] == {"x": 1}
    assert summary["n_diverged"] == 0
    table = rollout_table({"de": summary})
    assert "far off (diverged or R^2 < -10) | 1/2 | x (1)" in table
    clean = rollout_summary([scores[1]])
    assert clean["n_far_off"] == 0 and clean["far_off_states"] == {}
    assert "far off" not in rollout_table({"de": clean})


def test_table1_rows_carry_the_flag_without_changing_the_aggregation():
    table1 = load_script("table1.py", "table1_far_off")
    scores = [score({"x": X + 5.0, "y": Y}, DS), score({"x": X, "y": Y}, DS)]
    row = table1.summarise_recordings(scores)
    assert row["n_far_off"] == 1 and row["n_diverged"] == 0
    assert [r["far_off"] for r in row["per_recording"]] == [True, False]
    assert row["per_recording"][0]["far_off_states"] == ["x"]
    assert "far off 1/2" in table1._short(row)
