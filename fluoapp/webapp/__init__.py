"""The FluoGuide web application (trame-slicer): ``fluo app``."""
