"""The digital phantoms in Slicer's Sample Data module.

The phantoms are generated, not downloaded (``fluoguide.phantoms``). At
Slicer's start (:func:`register_on_startup`) each one is written once, as an
MRML scene (``CBCT`` and ``CBCTLabels``, the ground truth in their
``FluoGuide.Truth`` attribute), into Slicer's download cache
(:func:`sample_scene`), and registered as a Sample Data source whose file is
that scene: the Sample Data button and ``SampleData.downloadSample(name)`` both
find it in the cache and load it (Slicer's ``downloadFromSource`` ignores a
source's custom downloader, so one of those left ``downloadSample`` empty-handed).
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["CATEGORY", "SAMPLES", "load_phantom", "sample_scene", "sample_sources",
           "register_sample_data", "register_on_startup"]

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


#: the cache folder (under Slicer's download cache) of the phantoms' scenes
CACHE_FOLDER = "FluoGuide"


def sample_file_name(sample):
    """The sample's scene file relative to the download cache."""
    return f"{CACHE_FOLDER}/{sample}/scene.mrml"


def sample_scene(cache_dir, sample):
    """The scene file of Sample Data entry ``sample`` in ``cache_dir`` (written once:
    the phantom with its truth on both nodes, as :func:`load_phantom` makes it)."""
    from fluoguide import mrml_io

    path = Path(cache_dir) / sample_file_name(sample)
    if not path.is_file():
        scene = mrml_io.new_scene()
        load_phantom(scene, SAMPLES[sample][0])
        mrml_io.save_scene(scene, path)
    return path


def sample_sources(cache_dir):
    """The keyword arguments of ``SampleDataLogic.registerCustomSampleDataSource``
    for each phantom: a scene file already in the cache (nothing to download)."""
    out = []
    for sample, (_, description) in SAMPLES.items():
        scene = sample_scene(cache_dir, sample)
        out.append(dict(category=CATEGORY, sampleName=sample, uris=scene.as_uri(),
                        fileNames=sample_file_name(sample), nodeNames=None,
                        loadFiles=True, loadFileTypes="SceneFile",
                        thumbnailFileName=_thumbnail()))
    return out


def register_sample_data():
    """Register the phantoms with Sample Data (in the Slicer application; once)."""
    import slicer

    if getattr(slicer.modules, "fluoguideSampleDataRegistered", False):
        return
    import SampleData

    cache = slicer.mrmlScene.GetCacheManager().GetRemoteCacheDirectory()
    for kwargs in sample_sources(cache):
        SampleData.SampleDataLogic.registerCustomSampleDataSource(**kwargs)
    slicer.modules.fluoguideSampleDataRegistered = True


def register_on_startup():
    """In the Slicer application: register the phantoms once Slicer has started
    (Sample Data may load after our modules); outside it, nothing."""
    from fluoguide.slicer_compat import in_slicer_application

    if in_slicer_application():
        import slicer

        slicer.app.connect("startupCompleted()", register_sample_data)
