"""Tomography: analytic diffusion, FEM, meshing, reconstruction."""
