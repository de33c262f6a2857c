"""Clinical knee assessment from per-frame bone poses: joint angles, tibial-plateau-condyle
distances, medial-lateral differences, trajectories, plots and a report."""
