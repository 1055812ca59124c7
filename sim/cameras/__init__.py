"""The simulated cameras: the multi-view rig (poses, MuJoCo rendering, depth, masks), the choice of image renderer,
the reference pass over the empty workspace and the paper's occlusion ratio of a capture."""
