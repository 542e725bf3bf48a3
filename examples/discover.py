"""Discovery in ten lines of Python: the benchmark's recordings in, a model out, scored on a
fault it was not trained on.    python examples/discover.py"""

import jaxdmd
from jaxdmd.grid import benchmark_protocol

data = benchmark_protocol(generators=(31,), operating_points=4, noise=0.01, seed=0)
train, test = data.train[31], data.test[31]  # bus-15 fault (noisy) / bus-28 fault (clean)
model = jaxdmd.discover(train, test)  # DE loop, refits, AE loop: jaxdmd.DiscoveryConfig()
for lhs, rhs in {**model.de.readable(), **model.ae.readable()}.items():
    print(f"{lhs} = {rhs}")
print("held-out rollout R^2 (DAE):", model.score(test)["mean"]["r2"])
model.save("runs/example")  # model.py, equations.md, summary.json; jaxdmd.load() reads it back
