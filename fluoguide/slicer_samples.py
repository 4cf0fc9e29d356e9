"""The digital phantoms in Slicer's Sample Data module.

The phantoms are generated, not downloaded (``fluoguide.phantoms``): each
Sample Data button calls :func:`load_phantom`, which adds the phantom's
``CBCT`` and ``CBCTLabels`` (with the ground truth in ``FluoGuide.Truth``) to
the application's scene and shows them. Registered once per Slicer session by
:func:`register_sample_data`, which the module files connect to Slicer's
``startupCompleted()`` signal (:func:`register_on_startup`).
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["CATEGORY", "SAMPLES", "load_phantom", "register_sample_data", "register_on_startup"]

CATEGORY = "FluoGuide"
#: Sample name -> (phantom name, description)
SAMPLES = {
    "FluoGuideCylinderTube": ("cylinder-tube", "Cylinder with a fluorescent tube (4.7 mm deep)"),
    "FluoGuideOralCavity": ("oral-cavity", "Oral cavity with a fluorescent tongue"),
    "FluoGuideSlab": ("slab", "Homogeneous slab"),
}


def load_phantom(scene, phantom_name, **params):
    """Add phantom ``phantom_name`` to ``scene``; returns (CBCT node, label-map node)."""
    from fluoguide import mrml_io
    from fluoguide.phantoms import add_phantom_to_scene, make_phantom

    phantom = make_phantom(phantom_name, **params)
    add_phantom_to_scene(scene, phantom)
    cbct = mrml_io.get_node(scene, "CBCT")
    mrml_io.set_json_attribute(cbct, "FluoGuide.Truth", phantom.truth())
    return cbct, mrml_io.get_node(scene, "CBCTLabels")


def _thumbnail():
    # the FluoTomo icon: beside fluoguide/ in an installed extension
    # (qt-scripted-modules/Resources/Icons), in FluoTomo/ in the source tree
    root = Path(__file__).resolve().parent.parent
    for path in (root / "Resources" / "Icons" / "FluoTomo.png",
                 root / "FluoTomo" / "Resources" / "Icons" / "FluoTomo.png"):
        if path.is_file():
            return str(path)
    return None


def register_sample_data():
    """Register the phantoms with Sample Data (in the Slicer application; once)."""
    import slicer

    if getattr(slicer.modules, "fluoguideSampleDataRegistered", False):
        return
    import SampleData

    def loader(phantom_name):
        def load(source):
            cbct, labels = load_phantom(slicer.mrmlScene, phantom_name)
            slicer.util.setSliceViewerLayers(background=cbct, label=labels, fit=True)
            return [cbct, labels]

        return load

    for sample, (phantom_name, description) in SAMPLES.items():
        SampleData.SampleDataLogic.registerCustomSampleDataSource(
            category=CATEGORY, sampleName=sample, uris=f"fluoguide:phantom/{phantom_name}",
            fileNames=f"{phantom_name}.nrrd", nodeNames="CBCT", thumbnailFileName=_thumbnail(),
            customDownloader=loader(phantom_name))
    slicer.modules.fluoguideSampleDataRegistered = True


def register_on_startup():
    """In the Slicer application: register the phantoms once Slicer has started
    (Sample Data may load after our modules); outside it, nothing."""
    from fluoguide.slicer_compat import in_slicer_application

    if in_slicer_application():
        import slicer

        slicer.app.connect("startupCompleted()", register_sample_data)
