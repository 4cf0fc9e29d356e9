"""The FluoGuide application: the ``fluo`` command line, the demo and the web app.

The top layer: it may import the foundation (``fluoguide``) and every module Lib;
nothing below imports it.
"""
