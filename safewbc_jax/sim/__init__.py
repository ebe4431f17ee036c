"""Simulation loops: the MuJoCo (C) deployment loop; MJX batched rollouts."""
