"""The main job, ``fluo demo``: every stage end to end on the digital phantoms.

Modules
-------
- ``run``: The main job: ``fluo demo``, end to end on the digital phantoms.
- ``stages``: The stages of ``fluo demo`` (see demo.py for how they run).
"""
