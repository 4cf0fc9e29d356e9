"""FluoGuide: image-guided fluorescence quantification (shared foundation).

The three Slicer modules keep their real code in ``FluoCalibLib``,
``FluoNavLib`` and ``FluoTomoLib``; this package holds what all of them
stand on (errors, MRML scene I/O, the Slicer compatibility layer, digital
phantoms) and the ``fluo`` command line that joins them.
"""

__version__ = "0.1.0"
