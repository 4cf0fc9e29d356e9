"""Module parameter nodes: the state of a module's panel, kept in the MRML scene.

A parameter node is a ``vtkMRMLScriptedModuleNode`` with the singleton tag and
the ``ModuleName`` attribute of its module, as 3D Slicer's
``ScriptedLoadableModuleLogic.getParameterNode`` makes it; it holds string
parameters and node references, and is saved with the scene, so the panel
comes back as the user left it. FluoGuide's logics hold their scene
explicitly, so they get the node from that scene (never a global one) through
:func:`parameter_node`; the same code runs in Slicer, under pytest and in the
web app.

A module declares its parameters once, as a dict ``{name: default}``; the
default's Python type is the parameter's type (``str``, ``int``, ``float``,
``bool``), read back with :func:`get`. Node references (inputs and outputs
picked in node selectors) are set with ``SetNodeReferenceID`` and read with
``GetNodeReference``; they are not in the defaults dict.
"""

from __future__ import annotations

import math

from fluoguide.errors import FluoInputError

__all__ = ["parameter_node", "set_defaults", "get", "set_value", "parse_yields",
           "PARAMETER_CLASS"]

PARAMETER_CLASS = "vtkMRMLScriptedModuleNode"


def parameter_node(scene, module_name, defaults=None):
    """The module's parameter node in ``scene``, created (with ``defaults``) when missing.

    Parameters
    ----------
    scene : vtkMRMLScene
    module_name : str
        ``FluoCalib``, ``FluoNav``, ``FluoTomo``: the singleton tag and the
        ``ModuleName`` attribute, as Slicer's own logic base class sets them.
    defaults : dict, optional
        ``{parameter: default}``; parameters already set are kept.
    """
    if scene is None:
        raise ValueError("a parameter node needs an MRML scene")
    node = scene.GetSingletonNode(module_name, PARAMETER_CLASS)
    if node is None:
        node = scene.CreateNodeByClass(PARAMETER_CLASS)
        node.UnRegister(None)  # the Python variable owns it now (as in Slicer's base class)
        node.SetSingletonTag(module_name)
        node.SetName(scene.GenerateUniqueName(module_name))
        node.SetAttribute("ModuleName", module_name)
        node = scene.AddNode(node)
    elif node.GetAttribute("ModuleName") != module_name:
        # a scene closed in Slicer may drop the attribute; node selectors filter on it
        node.SetAttribute("ModuleName", module_name)
    if defaults:
        set_defaults(node, defaults)
    return node


def _text(value):
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    return str(value)


def set_defaults(node, defaults):
    """Set every parameter of ``defaults`` that the node does not have yet."""
    was = node.StartModify()
    try:
        for key, value in defaults.items():
            if not node.GetParameter(key):
                node.SetParameter(key, _text(value))
    finally:
        node.EndModify(was)


def set_value(node, key, value):
    """Store ``value`` (str, int, float or bool) as parameter ``key``."""
    node.SetParameter(key, _text(value))


def get(node, key, default):
    """Parameter ``key`` as the type of ``default`` (``default`` when unset).

    A value that does not parse as that type (a scene edited by hand) raises
    FluoInputError naming the node and the parameter.
    """
    text = node.GetParameter(key)
    if not text:
        return default
    kind = type(default)
    field = f"{node.GetName()}.{key}"
    if kind is bool:
        if text not in ("true", "false"):
            raise FluoInputError("parameter must be true or false", field=field, value=text)
        return text == "true"
    if kind in (int, float):
        try:
            value = kind(text)
        except ValueError:
            raise FluoInputError(f"parameter must be a number ({kind.__name__})", field=field,
                                 value=text) from None
        if kind is float and not math.isfinite(value):
            raise FluoInputError("parameter must be finite", field=field, value=text)
        return value
    return text


def parse_yields(text, field="yield"):
    """``LABEL:VALUE[,LABEL:VALUE...]`` (a yield per label, as a panel's text
    field or ``fluo tomo simulate --yield`` takes it) -> {label: yield [1/mm]}.

    Labels are integers >= 1, each given once; values finite and >= 0.
    Anything else raises FluoInputError naming ``field`` and the bad part.
    """
    out = {}
    for part in str(text).split(","):
        if not part.strip():
            continue
        lab, sep, val = part.partition(":")
        try:
            label, value = int(lab), float(val)
        except ValueError:
            raise FluoInputError("expected LABEL:VALUE[,LABEL:VALUE...] (yield in 1/mm)",
                                 field=field, value=text) from None
        if not sep or label <= 0:
            raise FluoInputError("expected LABEL:VALUE with a label >= 1", field=field,
                                 value=part)
        if not (math.isfinite(value) and value >= 0):
            raise FluoInputError("yield must be a finite number >= 0 [1/mm]",
                                 field=f"{field} {label}", value=val)
        if label in out:
            raise FluoInputError("label given twice", field=field, value=label)
        out[label] = value
    if not out:
        raise FluoInputError("expected LABEL:VALUE[,LABEL:VALUE...]", field=field, value=text)
    return out
