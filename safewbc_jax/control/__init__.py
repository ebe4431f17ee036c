"""The controller: task outputs and references, safe sets and their A-ECBF rows,
parameters, the scenario type, the QP terms and assembly, the one control step, its
metrics, the walking gait."""
