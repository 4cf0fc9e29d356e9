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
- ``scene``: ``fluo scene info SCENE.mrml``: what a scene holds (nodes, attributes, data); ``fluo scene import --cbct DIR|FILE --out DIR``: a scene from a CBCT (DICOM series folder or volume file).
- ``segment``: ``fluo segment --cbct DIR|FILE --thresholds SPEC --out LABELS.nrrd``: a CBCT's label map by HU thresholds.
- ``study``: ``fluo study A|B|C``: the thesis's 2D simulation studies.
"""

from contextlib import contextmanager

from fluoguide.errors import FluoInputError

#: the words of --grading (``fluo tomo reconstruct``, ``fluo validate mc-tomography``)
#: -> reconstruct_labelmap's ``grading``
GRADINGS = {"none": False, "grid": True, "bisection": "bisection"}


def module_logic(module, scene=None):
    """``<module>Logic`` of a module file (``FluoCalib``, ``FluoNav``, ``FluoTomo``)
    on ``scene`` (a new empty scene when None): the API every handler calls."""
    from fluoguide import mrml_io
    from fluoguide.slicer_compat import import_module_file

    return getattr(import_module_file(module), f"{module}Logic")(
        scene if scene is not None else mrml_io.new_scene())


def scene_for(path):
    """The MRML scene a ``--scene`` option names: loaded when the file exists, else new
    (saved there by :func:`save_scene_to`); a new scene when no path is given.
    A path that is not ``.mrml``, not writable or not a readable scene is refused."""
    from fluoguide import mrml_io

    if path:
        # checked before any work: a scene that cannot be read or written refuses
        # the run while nothing has been written
        return mrml_io.scene_to_update(path)
    return mrml_io.new_scene()


def save_scene_to(scene, path):
    """Save ``scene`` to ``path`` when a ``--scene`` option was given."""
    if path:
        from fluoguide import mrml_io

        mrml_io.save_scene(scene, path)



@contextmanager
def as_flags(names):
    """Name a refusal by the command's flags: the Lib checks name their
    parameters (``solver``, ``properties.mua_per_mm[0]``), a command its flags
    (``--solver``, ``--mua/--musp/--n.mua_per_mm[0]``). ``names``: {parameter:
    flag}; a field equal to a parameter, or starting with it and then ``.``,
    ``[`` or a space, is renamed; the problem, file and value are kept."""
    try:
        yield
    except FluoInputError as exc:
        field = exc.field if isinstance(exc.field, str) else None
        for name, flag in names.items():
            if field is not None and (field == name or field.startswith((f"{name}.", f"{name}[",
                                                                          f"{name} "))):
                raise FluoInputError(exc.problem, file=exc.file, field=flag + field[len(name):],
                                     value=exc.value) from exc
        raise
