"""Geometric calibration: boards, camera model and intrinsics, hand-eye, rigid transforms and
registration, undistortion, OpenCV YAML, synthetic board data.

Modules
-------
- ``boards``: Calibration boards: spec strings, 3D corner layout, texture and detection.
- ``files``: Reading the inputs of the geometric calibrations from files, checked: board image globs, tracked-pose JSON, point lists, intrinsics, 4x4 matrices.
- ``camera_model``: Camera intrinsics: projection of camera-frame points and back-projection of pixels.
- ``handeye``: Hand-eye calibration: camera frame to tracked camera-tool frame.
- ``intrinsics``: Intrinsic camera calibration from board images (Zhang's method via OpenCV).
- ``opencv_yaml``: OpenCV FileStorage YAML of camera intrinsics and hand-eye results.
- ``registration``: Paired-point rigid registration (Horn 1988) and pivot calibration.
- ``scene``: Geometric calibration results in the MRML scene (see docs/scene.md).
- ``synthetic_boards``: Synthetic calibration data with known truth: board images and tracked tool poses.
- ``transforms``: Rigid 4x4 transforms, rotations and quaternions.
- ``undistort``: Undistortion maps for live video (computed once per camera, cached).
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "boards": ["Board", "parse_board", "Detection"],
    "camera_model": ["CameraModel"],
    "files": ["image_files", "read_points", "read_matrix", "read_intrinsics", "read_handeye_poses"],
    "handeye": ["OPENCV_METHODS", "METHODS", "check_motion", "solve_handeye", "paired_point_handeye", "handeye_errors", "compare_methods", "board_to_tracker_from_pointer", "estimate_board_to_tracker", "MIN_ROTATION_DEG"],
    "intrinsics": ["ViewResult", "IntrinsicsResult", "detect_views", "calibrate_camera", "calibrate_from_detections", "view_poses", "reprojection_errors", "MIN_VIEWS", "PARALLEL_VIEWS_DEG"],
    "opencv_yaml": ["write_calibration_yaml", "read_calibration_yaml"],
    "registration": ["MAX_COORDINATE_MM", "check_points", "RegistrationResult", "register_points", "target_registration_error", "pivot_calibration"],
    "scene": ["CALIBRATION_NODE", "INTRINSICS_KEY", "HANDEYE_KEY", "REGISTRATION_KEY", "HANDEYE_TRANSFORM", "LEGACY_HANDEYE_TRANSFORMS", "TOOL_TRANSFORM", "REGISTRATION_TRANSFORM", "calibration_node", "store_intrinsics", "load_intrinsics", "intrinsics_doc", "store_handeye", "handeye_node", "load_handeye", "store_registration"],
    "synthetic_boards": ["SyntheticView", "random_board_poses", "render_view", "make_dataset", "default_camera", "default_camera_to_tool"],
    "transforms": ["make_rigid", "invert_rigid", "apply_rigid", "rotation_matrix", "rotvec_to_matrix", "matrix_to_rotvec", "matrix_to_quaternion", "quaternion_to_matrix", "slerp", "look_at", "is_rigid", "as_rigid", "as_rigid_list", "orthonormalize", "rotation_angle"],
    "undistort": ["undistort_maps", "undistort_image", "clear_cache"],
})
