"""A first-order state that tracks a slow angle, with a clean algebraic channel: the test
system of the algebraic selection (tests/test_select.py) and of the refit by simulation
(tests/test_simfit.py)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from jaxdmd.data import Dataset


def tracking(
    n: int, noise: float, gain: float, samples: int, rates: tuple[float, float, float, float],
    seed: int = 0, amplitude: float = 0.3, curve: Callable[[np.ndarray], np.ndarray] | None = None,
) -> list[Dataset]:  # fmt: skip
    """d x/dt = u - y with y = gain (x - theta), ``n`` recordings over 10 s: recording k has
    theta = ``amplitude`` sin((a + b k) t + k) and u = 1 + 0.5 sin((c + d k) t + 2 k) with
    ``rates = (a, b, c, d)``, x starts on its equilibrium and is integrated by fine Euler steps
    (the truth), then recorded with ``noise`` x its range (generator ``seed + k``); u, theta
    and y are clean. With ``curve``, x tracks ``curve(theta)`` instead: y = gain (x -
    curve(theta))."""
    f = curve or (lambda v: v)
    a, b, c, d = rates
    t = np.linspace(0.0, 10.0, samples)
    out = []
    for k in range(n):
        rng = np.random.default_rng(seed + k)
        theta = amplitude * np.sin((a + b * k) * t + k)
        u = 1.0 + 0.5 * np.sin((c + d * k) * t + 2 * k)
        x = np.empty_like(t)
        x[0] = f(theta[0]) + u[0] / gain
        for i in range(t.size - 1):
            xi, h = x[i], (t[i + 1] - t[i]) / 50
            for m in range(50):
                w = m / 50
                th, uu = (1 - w) * theta[i] + w * theta[i + 1], (1 - w) * u[i] + w * u[i + 1]
                xi += h * (uu - gain * (xi - f(th)))
            x[i + 1] = xi
        channels = {
            "x": x + noise * np.ptp(x) * rng.normal(size=t.shape),
            "u": u,
            "theta": theta,
            "y": gain * (x - f(theta)),
        }
        roles = {"x": "state", "u": "input", "theta": "input", "y": "algebraic"}
        out.append(Dataset.create(t, channels, roles))
    return out
