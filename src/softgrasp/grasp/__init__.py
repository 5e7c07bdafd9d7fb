"""Grasp mechanics of rigid-body point contacts: static equilibrium, friction cones, force closure."""
