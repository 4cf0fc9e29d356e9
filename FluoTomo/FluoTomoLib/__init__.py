"""FluoTomo's library: fluorescence tomography from a CBCT label map.

Subpackages (one per concept):

- ``meshing``: label map to tetrahedral mesh (structured, voxel, fTetWild), mesh I/O;
- ``fem``: the diffusion finite-element model, its solvers and Jacobians;
- ``recon``: reconstruction of fluorescence yield with no, soft and hard priors;
- ``acquisition``: simulated tracked scans, non-contact optodes, camera frames;
- ``pipelines``: image-guided tomography end to end on a scene;
- ``studies``: the thesis's 2D simulation studies.

Modules: ``optics`` (diffusion-theory optical quantities), ``analytic`` (closed-form
half-space solutions), ``scene`` (results into the MRML scene).
"""
