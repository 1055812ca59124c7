"""Motion execution: minimum-jerk trajectories, IK with mink, the pick sequence and the success test."""
