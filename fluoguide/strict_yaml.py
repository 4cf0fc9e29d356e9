"""YAML read strictly: a key given twice in one mapping is refused.

PyYAML's ``safe_load`` keeps the last of two equal keys and OpenCV's
FileStorage the first, both without a word, so a study, batch or calibration
file edited by hand could mean two things. The document is composed (parsed to
nodes, nothing constructed) and every mapping's keys compared before it is
loaded; the message names the file, the path of keys and the line.
"""

from __future__ import annotations

import re

from fluoguide.errors import FluoInputError

_MERGE_TAG = "tag:yaml.org,2002:merge"


def check_duplicate_keys(text, file=None, field=None):
    """Refuse YAML ``text`` in which a mapping has a key twice.

    Parameters
    ----------
    text : str
        YAML text (OpenCV's ``%YAML:1.0`` header is accepted).
    file : str or Path, optional
        Where the text came from, for the message.
    field : str, optional
        What the file is (an option), put before the path of keys.

    Raises
    ------
    FluoInputError
        The file, ``field: path.of.keys`` and the key, with its line.
    yaml.YAMLError, RecursionError
        When the text is not YAML (the caller words it).

    Notes
    -----
    Keys are compared as written (scalar text), so ``1`` and ``"1"`` count as
    the same key here although YAML types them apart: a file that relies on that
    is ambiguous to a reader too. Keys brought in by a merge (``<<: *base``) may
    be overridden; that is what a merge is for.
    """
    import yaml

    # OpenCV writes "%YAML:1.0", a directive PyYAML does not parse
    text = re.sub(r"\A%YAML:1\.0", "%YAML 1.1", text)
    for root in yaml.compose_all(text, Loader=yaml.SafeLoader):
        stack = [(root, "")]
        seen_nodes = set()          # an alias repeats a node (or makes a cycle): once each
        while stack:
            node, path = stack.pop()
            if id(node) in seen_nodes:
                continue
            seen_nodes.add(id(node))
            if isinstance(node, yaml.MappingNode):
                seen = {}
                children = []
                for key_node, value_node in node.value:
                    if key_node.tag == _MERGE_TAG:
                        continue
                    key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
                    if key is not None:
                        if key in seen:
                            where = f"{path}.{key}" if path else key
                            raise FluoInputError(
                                f"key given twice in one YAML mapping (lines "
                                f"{seen[key] + 1} and {key_node.start_mark.line + 1}; YAML "
                                "readers silently keep one of them): give it once",
                                file=file, field=": ".join(w for w in (field, where) if w),
                                value=key)
                        seen[key] = key_node.start_mark.line
                    children.append((value_node, f"{path}.{key}" if path else str(key)))
                stack.extend(reversed(children))
            elif isinstance(node, yaml.SequenceNode):
                stack.extend(reversed([(v, f"{path}[{i}]") for i, v in enumerate(node.value)]))


def load(text, file=None, field=None):
    """``yaml.safe_load(text)`` after :func:`check_duplicate_keys`."""
    import yaml

    check_duplicate_keys(text, file=file, field=field)
    return yaml.safe_load(text)
