"""From a CSV recording and a classical model to the discrepancy report.

The path of an engineer whose simulation does not match a disturbance recording:

1. the recordings: CSV files with a JSON sidecar naming each column's role (here simulated by
   jaxdmd's IEEE 39-bus benchmark, standing in for PMU data: generator 31, a plant with a
   damper winding the model lacks, three bus-15 faults and one bus-28 fault);
2. the model: the textbook classical machine (or your own skeleton file, see docs/diagnose.md);
3. ``diagnose``: what the simulation gets wrong, the cause, the extended model, the gain;
4. the report: ``report.md``, ``trajectories.png``, ``evidence.png``, ``diagnosis.json``.

    python examples/diagnose_your_model.py [--out DIR] [--rounds N]

The same from the command line, on the CSV files this script writes:

    python -m jaxdmd.run diagnose --data DIR/recordings/train_*.csv \\
        --test-data DIR/recordings/test_0.csv --model classical --out DIR/report
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax

from jaxdmd.data import Dataset
from jaxdmd.diagnose import DiagnoseConfig, builtin_model, diagnose, write_report
from jaxdmd.grid import MachineModel, paper_protocol


def write_recordings(folder: Path) -> tuple[list[Path], list[Path]]:
    """Stand-in for your PMU exports: CSV + JSON sidecar per recording."""
    plant = MachineModel(name="classical", damping=20.0)  # the effect the model lacks
    data = paper_protocol(n_train=3, n_test=1, noise=0.005, model=plant, generators=(31,))
    folder.mkdir(parents=True, exist_ok=True)
    train = [ds.save(folder / f"train_{i}.csv") for i, ds in enumerate(data.train[31])]
    test = [ds.save(folder / f"test_{i}.csv") for i, ds in enumerate(data.test[31])]
    return train, test


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runs/diagnose-example")
    parser.add_argument("--rounds", type=int, default=8)
    args = parser.parse_args()
    out = Path(args.out)

    train_files, test_files = write_recordings(out / "recordings")
    train = [Dataset.load(p) for p in train_files]  # the columns' roles come from the sidecar
    test = [Dataset.load(p) for p in test_files]
    print(f"channels: {', '.join(train[0].names)}; states: {', '.join(train[0].state_names)}")

    model = builtin_model("classical", channels=train[0].names)
    print(f"model under test:\n{model.source}")
    result = diagnose(
        train, model, test=test, key=jax.random.key(0), config=DiagnoseConfig(rounds=args.rounds)
    )
    report = write_report(out / "report", result)

    print(f"cause ({result.cause.kind}): {result.cause.summary}")
    if result.extended is not None:
        for lhs, rhs in result.extended.readable().items():
            print(f"  {lhs} = {rhs}")
    print(f"held-out error ratio before/after: {result.gain:.1f}x; report: {report}")


if __name__ == "__main__":
    main()
