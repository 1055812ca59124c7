"""MuJoCo side of torm: robot models and configs, scenes, simulated cameras and the simulated backend."""
