"""Live devices: the NDI serial protocol, client and simulator, OpenIGTLink, USB discovery,
camera frame sources, the live loop, recording and replay, time synchronisation.

Modules
-------
- ``frame_sources``: Camera frame sources: a UVC camera or video file (OpenCV ``VideoCapture``), a folder of images, a FluoGuide recording, or synthetic frames.
- ``frame_store``: Tracked camera frames in the MRML scene: the one format that recording, replay, the live loop and ``fluo nav correct`` share (see docs/scene.md).
- ``igtl_client``: OpenIGTLink input (from PLUS or any server) into the MRML scene, as SlicerOpenIGTLink maps it: a TRANSFORM message named ``CameraToolToTracker`` updates (or creates) the linear transform node of that name, an IMAGE message updates the scalar volume node of its device name, and each node carries the message time in the attribute ``FluoNav.IGTLTimestamp``.
- ``live_loop``: The live loop: tracker poses + camera frames -> one callback per frame.
- ``ndi_client``: NDI tracker client over pyserial: set-up, tracking loop, fault recovery and an exact account of every frame.
- ``ndi_protocol``: NDI Combined API (Polaris/Aurora) serial protocol: commands, replies, CRC.
- ``ndi_simulator``: A protocol-faithful simulated NDI tracker on a pseudo-terminal.
- ``recorder``: Recording tracked frames to disk incrementally, and replaying them.
- ``recording``: Tracked camera frames recorded to a folder through the live loop, with the simulated tracker.
- ``tracker``: One interface over the pose sources: an NDI tracker on a serial port (or the simulator on a pseudo-terminal), an OpenIGTLink server, a recording.
- ``timesync``: Time synchronisation of tracker poses to camera frames.
- ``usb``: Find attached NDI trackers and cameras: serial ports (pyserial's ``list_ports``) and USB devices (pyusb), by vendor/product id and USB class.
"""

from fluoguide.lazy import attach

__getattr__, __dir__, __all__ = attach(__name__, {
    "frame_sources": ["Frame", "OpenCVSource", "ImageSequenceSource", "RecordingSource", "SyntheticSource", "IMAGE_SUFFIXES"],
    "frame_store": ["FRAME_SEQUENCE", "LOG_TABLE", "BASE_COLUMNS", "new_recording", "append_tracked_frame", "number_of_frames", "read_tracked_frame", "recording_tools"],
    "igtl_client": ["IGTLReceiver", "TIMESTAMP_ATTRIBUTE"],
    "live_loop": ["LiveLoop"],
    "ndi_client": ["NDIClient", "TrackingStats"],
    "ndi_protocol": ["NDIProtocolError", "crc16", "with_crc", "check_reply", "command", "ToolPose", "TXReply", "parse_tx", "format_tx", "parse_phsr", "format_phsr", "ERROR_CODES", "PORT_OCCUPIED", "PORT_ENABLED", "PORT_OUT_OF_VOLUME", "PORT_PARTIAL_OUT_OF_VOLUME"],
    "ndi_simulator": ["Faults", "SimTool", "NDISimulator", "FAULT_KINDS"],
    "recording": ["frame_source", "record_simulated"],
    "recorder": ["Recorder", "read_recording", "replay", "to_scene"],
    "timesync": ["PoseBuffer", "estimate_latency"],
    "tracker": ["SOURCES", "TrackerSession", "NDITracker", "IGTLTracker", "ReplayTracker", "open_tracker", "check_seconds", "parse_host_port", "finite_pose"],
    "usb": ["NDI_USB_IDS", "CAMERA_VENDORS", "UVC_CLASS", "discover", "classify_usb"],
})
