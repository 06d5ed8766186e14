"""Config groups of the experiments: experiment, ablate and perturbation."""
