"""Surface mapping: per-pixel ray casting onto the CBCT surface, the navigated illumination
model, transport and surface-flux images, contour classification, frame correction.

Modules
-------
- ``benchmark``: Speed and accuracy of per-pixel surface mapping (``fluo bench mapping``, ``python -m benchmarks mapping``): full-resolution and binned frames, full and decimated surfaces, on the oral-cavity phantom with homogeneous fluorescence.
- ``contours``: Contour-based tissue classification and its miss rate (docs/physics.md section 6.3).
- ``correct``: Correct recorded tracked frames with the navigated illumination model (``fluo nav correct``): everything it needs comes from the MRML scene.
- ``flux_map``: The navigated illumination model on ray-cast pixels (docs/physics.md section 6.1).
- ``illumination_kernel``: The illumination cone evaluated per pixel in one compiled pass (video rate).
- ``kernels``: The compiled (numba) surface-mapping kernels made ready before long work uses them, with progress.
- ``mismatch``: Surface-flux mapping validated on data it did not make itself: frames rendered on a finer true surface from true poses, corrected with the CBCT surface and tracked poses (tracking and hand-eye error).
- ``pixel_cast``: Every camera pixel's ray cast onto the tissue surface.
- ``rasterize``: Primary-ray casting by z-buffer rasterisation (the video-rate path).
- ``scene``: Surface-flux mapping results in the MRML scene (docs/scene.md).
- ``surface``: The air-tissue surface of a CBCT (its intensities, or its label map), for ray casting and display.
- ``synthetic``: A synthetic navigated acquisition on the oral-cavity phantom: homogeneous fluorescence (uniform transport T), a light coupled to the camera, tracked views looking into the cavity, camera noise — the data with known truth that the surface-flux mapping is tested and benchmarked on.
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "benchmark": ["run_mapping_benchmark"],
    "contours": ["miss_rate", "overlay_png"],
    "correct": ["NavContext", "FrameResult", "load_context", "read_frame", "correct_image", "correct_frame", "map_frames_to_surface"],
    "flux_map": ["ViewModel", "view_model", "forward_image", "transport_image", "surface_flux", "accumulate_on_faces", "plane_hits"],
    "illumination_kernel": ["cone_factors_from_cast"],
    "kernels": ["prepare_kernels"],
    "mismatch": ["MISMATCH_CASES", "mapping_under_mismatch", "mismatch_figure"],
    "pixel_cast": ["SurfaceCaster", "PixelHits", "cast_camera", "reference_cast"],
    "rasterize": ["RayGrid", "raster_cast"],
    "scene": ["SURFACE_NODE", "TRANSPORT_NODE", "RAW_NODE", "FLUX_NODE", "MAPPING_KEY", "write_surface_flux", "write_frame_images", "point_means"],
    "surface": ["surface_from_cbct", "surface_from_cbct_node", "surface_from_labelmap", "surface_from_labelmap_node"],
    "synthetic": ["oral_cavity_surface", "open_field_camera", "coupled_light", "view_poses", "look_at_cavity", "stream_camera_tool", "render_view", "render_hits", "exact_oral_cavity_hits", "PoseError", "tracked_acquisition"],
})
