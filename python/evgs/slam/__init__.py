"""The SLAM pipeline's building blocks (paper §3): SE(3) maths and the continuous trajectory, the
Gaussian scene, the event loss, densification/pruning and the guards against known failure modes."""
