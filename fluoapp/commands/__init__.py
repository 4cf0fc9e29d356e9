"""The ``fluo`` subcommands: each module registers its parsers and is a thin caller of the logic.

Modules
-------
- ``app``: ``fluo app``: serve the web application.
- ``calib_geometry``: ``fluo calib camera | handeye | register | pivot | synth-boards``: geometric calibration CLI.
- ``calib_light``: ``fluo calib radiometry|illumination|laser|synth-light``: radiometric calibrations from image stacks and images (synthetic sets with known truth from ``synth-light``).
- ``demo``: ``fluo demo --out DIR [--quick]``: the end-to-end main job.
- ``devices``: ``fluo devices``, ``fluo track``, ``fluo record``, ``fluo replay``: find trackers and cameras, track poses, record and replay tracked frames.
- ``fem``: ``fluo analytic`` and ``fluo forward``: diffusion theory and the FEM from the shell.
- ``mesh``: ``fluo mesh LABELMAP --out MESH.vtu``: label map to a tetrahedral mesh with regions.
- ``nav``: ``fluo nav synth|correct`` and ``fluo bench mapping``: surface-flux mapping of tracked fluorescence frames (docs/surface-mapping.md).
- ``phantom``: ``fluo phantom NAME --out DIR``: write a digital phantom as an MRML scene.
- ``scene``: ``fluo scene info SCENE.mrml``: what a scene holds (nodes, attributes, data).
- ``study``: ``fluo study A|B|C``: the thesis's 2D simulation studies.
"""
