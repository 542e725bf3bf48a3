"""Relations among the algebraic variables' measurements (jaxdmd.identities)."""

from __future__ import annotations

import ast

import jax
import numpy as np
from tracking import tracking

import jaxdmd  # noqa: F401  (float64)
from jaxdmd import lines as ln
from jaxdmd import search
from jaxdmd.data import Dataset
from jaxdmd.identities import (
    Identity,
    fitted_nmse,
    measured_identities,
    with_identities,
)
from jaxdmd.problems import ae_problem, de_problem
from jaxdmd.select import _assemble

RATES = (0.2, 0.05, 0.3, 0.1)


def _with_power(recordings: list[Dataset], losses: float = 0.05) -> list[Dataset]:
    """The tracking recordings (x noisy, y = 20 (x - theta) clean) with two more clean
    algebraic channels: w = 2 + cos(theta), and a power P = y w + ``losses`` y^2."""
    out = []
    for ds in recordings:
        channels = {n: np.asarray(ds[n]) for n in ds.names}
        channels["w"] = 2.0 + np.cos(channels["theta"])
        channels["P"] = channels["y"] * channels["w"] + losses * channels["y"] ** 2
        roles = {n: ds.role(n) for n in ds.names} | {"w": "algebraic", "P": "algebraic"}
        out.append(Dataset.create(ds.t, channels, roles).with_estimated_derivatives())
    return out


def _state_and_lines(recordings: list[Dataset], texts: dict[str, str]):
    """The AE problem of y, w and P (a DE library that reads them) and its equations with the
    given lines in the states."""
    _, contract = de_problem(recordings, matched=True, library=("u", "y", "w", "P", "theta"))
    problem, ae_contract = ae_problem(recordings, contract)
    state = search.init(problem, ae_contract, jax.random.key(0), search.SearchConfig())
    lines = [
        ln.Line(ast.parse(texts[t], mode="eval").body, texts[t].count("p["))
        for t in ae_contract.targets
    ]
    equations = _assemble(state, lines)
    assert equations is not None
    return state, equations


def test_a_power_that_is_a_product_of_the_other_channels_is_found_with_its_losses():
    """P = y w + 0.05 y^2 on the measurements, but its line in the states can only be a stand-in
    (x and theta are noisy or enter nonlinearly): the relation must be found, with both terms
    and their coefficients, and its held-out error must be far below the line's. w's line in
    the states is exact (2 + cos theta), so no relation is reported for w."""
    recordings = _with_power(tracking(3, 0.01, 20.0, 1001, RATES))
    state, equations = _state_and_lines(
        recordings,
        {
            "y": "p[0] * x + p[1] * theta",
            "w": "p[0] + p[1] * jnp.cos(theta)",
            "P": "p[0] + p[1] * x + p[2] * theta",
        },
    )
    found = {i.target: i for i in measured_identities(state, equations)}
    assert "P" in found and "w" not in found
    power = found["P"]
    terms = dict(zip(power.factors, power.coefficients, strict=True))
    assert set(terms) == {("y", "w"), ("y", "y")}, power.text()
    assert abs(terms[("y", "w")] - 1.0) < 1e-6 and abs(terms[("y", "y")] - 0.05) < 1e-6
    assert power.held_out_nmse < 1e-12 < 1e-3 < power.line_nmse
    assert power.text(3) == "P = 1 y w + 0.05 y^2"
    # equations.md's table: the relation and both errors
    from jaxdmd.report import identities_section

    rows = [r for r in identities_section({power.target: power.as_dict()}) if r.startswith("| P")]
    assert rows == [f"| {power.text()} | < 1e-12 | {power.line_nmse:.2g} | no |"]


def test_no_relation_where_the_channels_are_unrelated():
    """P here is a channel of its own (a slow sine in time, not a function of y and w): no sum
    of their products fits it better than its line, so nothing is reported for it."""
    recordings = []
    for k, ds in enumerate(_with_power(tracking(3, 0.01, 20.0, 1001, RATES))):
        channels = {n: np.asarray(ds[n]) for n in ds.names}
        channels["P"] = np.sin((0.7 + 0.1 * k) * ds.t + k)
        recordings.append(
            Dataset.create(
                ds.t, channels, {n: ds.role(n) for n in ds.names}
            ).with_estimated_derivatives()
        )
    state, equations = _state_and_lines(
        recordings,
        {
            "y": "p[0] * x + p[1] * theta",
            "w": "p[0] + p[1] * jnp.cos(theta)",
            "P": "p[0] * u + p[1] * theta",
        },
    )
    assert "P" not in {i.target for i in measured_identities(state, equations)}


def _power_written(y_line: str):
    """Clean recordings (x without noise), y's line ``y_line``, w's exact, P's a stand-in: the
    state, the equations, P's relation found on the measurements, and the equations with it
    written in (:func:`with_identities`)."""
    recordings = _with_power(tracking(3, 0.0, 20.0, 1001, RATES))
    state, equations = _state_and_lines(
        recordings,
        {"y": y_line, "w": "p[0] + p[1] * jnp.cos(theta)", "P": "p[0] + p[1] * x + p[2] * theta"},
    )
    (power,) = [i for i in measured_identities(state, equations) if i.target == "P"]
    return state, equations, power, with_identities(equations, [power], state)


def test_a_relation_written_into_the_model_reads_the_other_lines_and_fits_far_better():
    """The relation found above, written in place of P's stand-in line: the skeleton computes P
    from y's and w's outputs by name, with the relation's coefficients as parameters, so that
    P in the states (inlined) reads nothing measured, and that line's NMSE on the problem is far
    below the stand-in's; the other lines and their parameters are kept. (x clean here: the
    relation's line is as good as the lines it reads.) A relation that reads a variable
    written as a relation is refused."""
    state, equations, power, written = _power_written("p[0] * x + p[1] * theta")
    assert written is not None
    targets = list(equations.contract.targets)
    j = targets.index("P")
    assert written.params[-len(power.coefficients) :] == power.coefficients
    assert "P_ = p[" in written.source and "y_ * w_" in written.source, written.source
    lines, maps = ln.split_lines(written.source)
    assert lines[j].variables() - {"jnp"} <= {"x", "theta"}  # nothing measured
    # shown as the relation it is (equations.md, the terminal), in the states in summary.json
    shown, inlined = written.readable(by_name=True)["P"], written.readable()["P"]
    assert "y * w" in shown and "x" not in shown and "y" not in inlined, (shown, inlined)
    assert equations.readable(by_name=True) == equations.readable()
    assert written.losses[j] < equations.losses[j] / 10, (written.losses, equations.losses)
    # the model's fits as they are: the equations' losses (both fitted on this problem)
    assert np.allclose(fitted_nmse(equations, state), equations.losses, rtol=1e-6, atol=1e-20)
    assert np.allclose(fitted_nmse(written, state), written.losses, rtol=1e-6, atol=1e-20)
    old_lines, old_maps = ln.split_lines(equations.source)
    for k, target in enumerate(targets):
        if target != "P":  # the other lines and their parameters as they were
            assert lines[k].text == old_lines[k].text
            assert [written.params[i] for i in maps[k]] == [
                equations.params[i] for i in old_maps[k]
            ]
            assert written.losses[k] == equations.losses[k]
    # y written as a relation that P's relation reads: refused
    circular = Identity("y", (("w", "w"),), (1.0,), 0.0, 1.0)
    assert with_identities(equations, [circular, power], state) is None


def test_a_relation_in_stand_in_lines_fits_worse_than_the_variables_own_line():
    """The same exact relation P = y w + 0.05 y^2, but y's line in the states is a stand-in
    (``p[0] * theta``: it misses x). On the measurements the relation is still found, but
    written in the model's lines it passes through y's stand-in and fits P far worse than P's
    own line: that is what keeps it out of the model."""
    state, equations, _, written = _power_written("p[0] * theta")
    j = list(equations.contract.targets).index("P")
    assert written is not None
    assert written.losses[j] > 100 * fitted_nmse(equations, state)[j]
