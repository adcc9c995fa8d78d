"""`fixego demo`: the live pipeline on the simulated rig, as separate processes, and its report."""
