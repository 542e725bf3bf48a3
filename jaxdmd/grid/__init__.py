"""The IEEE 39-bus benchmark: case39 network, Newton power flow, OPF operating points, machine
models (PSAT 5.1 and simpler ones) with optional controls, fault simulation with diffrax, and the
paper's experiment (:func:`paper_protocol`). See docs/benchmark-system.md for every number.
"""

from jaxdmd.grid.benchmark import benchmark_protocol
from jaxdmd.grid.machines import (
    MODEL_STATES,
    STATE_LAYOUT,
    Exciter,
    Governor,
    MachineModel,
    MachineParams,
    canonical_model_name,
    machine_params,
)
from jaxdmd.grid.network import BASE_MVA, FREQUENCY_HZ, OMEGA_B, Case, case39, newton_pf
from jaxdmd.grid.operating import (
    OperatingPoint,
    nominal_operating_point,
    operating_points,
    opf_operating_point,
)
from jaxdmd.grid.protocol import (
    ProtocolData,
    generator_channels,
    generator_dataset,
    paper_protocol,
)
from jaxdmd.grid.simulate import (
    ALGEBRAIC,
    Fault,
    SimResult,
    SolverSettings,
    SynchronismWarning,
    out_of_step,
    simulate,
)

__all__ = [
    "ALGEBRAIC",
    "BASE_MVA",
    "FREQUENCY_HZ",
    "MODEL_STATES",
    "OMEGA_B",
    "STATE_LAYOUT",
    "Case",
    "Exciter",
    "Fault",
    "Governor",
    "MachineModel",
    "MachineParams",
    "OperatingPoint",
    "ProtocolData",
    "SimResult",
    "SolverSettings",
    "SynchronismWarning",
    "benchmark_protocol",
    "canonical_model_name",
    "case39",
    "generator_channels",
    "generator_dataset",
    "machine_params",
    "newton_pf",
    "nominal_operating_point",
    "operating_points",
    "opf_operating_point",
    "out_of_step",
    "paper_protocol",
    "simulate",
]
