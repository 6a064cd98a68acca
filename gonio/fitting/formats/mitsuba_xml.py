"""A fitted model as Mitsuba 3 XML: a snippet to paste into a scene, or a file of its own.

Mitsuba 3's XML parser (``src/core/xml.cpp``, "Scene format" in its documentation) needs a
``version`` attribute on the root element of every file it loads, ``mitsuba.load_file`` and
``<include filename="..."/>`` alike, and refuses it on any other element ("unexpected
attribute"). So the two forms differ only there:

* :func:`mitsuba_snippet`: ``<bsdf type=... id=...>`` without ``version``, to paste inside a
  ``<scene version="3.0.0">``;
* :func:`mitsuba_document`: the same ``<bsdf>`` as the root of a file, with
  ``version="3.0.0"`` (:data:`MITSUBA_XML_VERSION`, the scene-format version of Mitsuba 3,
  which 3.x parsers read without upgrading it). ``mitsuba.load_file`` returns the BSDF;
  a scene that includes the file can use it as ``<ref id="gonio_fit"/>``.

Attribute values are XML-escaped (``xml.sax.saxutils.quoteattr``); comments never hold ``--``.
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import numpy as np

import gonio.models as gm

__all__ = ["MITSUBA_XML_VERSION", "mitsuba_document", "mitsuba_snippet"]

#: The ``version`` of Mitsuba 3's scene format written on a file's root element.
MITSUBA_XML_VERSION = "3.0.0"


def _fmt_float(v) -> str:
    return repr(float(v))


def _rgb(key, value, indent) -> str:
    v = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,))
    return f'{indent}<rgb name={quoteattr(key)} value="{", ".join(_fmt_float(x) for x in v)}"/>'


def _xml_lines(d: dict, indent: str) -> list[str]:
    lines = []
    for key, value in d.items():
        if key in ("type", "id"):
            continue
        if isinstance(value, dict):
            kind = value.get("type")
            if kind == "rgb":
                lines.append(_rgb(key, value["value"], indent))
            elif kind == "spectrum" and not isinstance(value.get("value"), (list, tuple)):
                lines.append(f'{indent}<spectrum name={quoteattr(key)} value="{_fmt_float(value["value"])}"/>')
            else:  # a nested plugin: a BSDF (blendbsdf's lobes), a texture, ... as Mitsuba knows it
                from gonio.models.mitsuba import plugin_kind

                tag = plugin_kind(str(kind))
                lines.append(f"{indent}<{tag} type={quoteattr(str(kind))} name={quoteattr(key)}>")
                lines.extend(_xml_lines(value, indent + "    "))
                lines.append(f"{indent}</{tag}>")
        elif isinstance(value, (bool, np.bool_)):
            lines.append(f'{indent}<boolean name={quoteattr(key)} value="{"true" if value else "false"}"/>')
        elif isinstance(value, (int, np.integer)):
            lines.append(f'{indent}<integer name={quoteattr(key)} value="{int(value)}"/>')
        elif isinstance(value, (float, np.floating)):
            lines.append(f'{indent}<float name={quoteattr(key)} value="{_fmt_float(value)}"/>')
        elif isinstance(value, str):
            lines.append(f"{indent}<string name={quoteattr(key)} value={quoteattr(value)}/>")
        elif isinstance(value, (list, tuple, np.ndarray)) and np.size(value) == 3:
            lines.append(_rgb(key, value, indent))
        else:
            raise TypeError(f"cannot write Mitsuba property {key!r} of type {type(value).__name__} as XML")
    return lines


def _comment(text: str) -> str:
    return "<!-- " + text.replace("--", "- -") + " -->"


def _bsdf_lines(model_name, options, params, bsdf_id, version):
    model = gm.get(model_name, **(options or {}))
    d = model.to_mitsuba(params)
    kind = str(d["type"])
    lines = [_comment(f"gonio fit: model {model.name}, options {dict(model.options)}; f_r in sr^-1."
                      " Exterior index 1 (ext_ior) where the model has one.")]
    if kind.startswith("gonio_"):
        lines.append(_comment(f"'{kind}' is a Python BSDF: call gonio.models.get({model.name!r}).to_mitsuba(params)"
                              " (which runs mitsuba.register_bsdf) before loading this scene."))
    root = f" version={quoteattr(version)}" if version else ""
    lines.append(f"<bsdf type={quoteattr(kind)} id={quoteattr(bsdf_id)}{root}>")
    lines.extend(_xml_lines(d, "    "))
    lines.append("</bsdf>")
    return lines, d


def mitsuba_snippet(model_name: str, options: dict | None, params: dict, *, bsdf_id: str = "gonio_fit"):
    """A fitted model as a Mitsuba 3 ``<bsdf>`` XML snippet and the equivalent Python dict.

    Parameters
    ----------
    model_name : str
        A gonio model name (``gonio.models.names()``).
    options : dict or None
        The model's discrete options (``{"distribution": "ggx"}``).
    params : dict
        Fitted parameter values.
    bsdf_id : str
        The ``id`` of the XML element (to reference it from a shape).

    Returns
    -------
    xml_text : str
        ``<bsdf type=... id=...>...</bsdf>`` to paste inside a Mitsuba 3 ``<scene>``; it has
        no ``version`` attribute, which Mitsuba refuses below a file's root (a file of its own:
        :func:`mitsuba_document`).
    mitsuba_dict : dict
        ``mitsuba.load_dict`` accepts it as is.

    Notes
    -----
    Models without a native Mitsuba plugin export a Python plugin ``gonio_<name>``: the
    snippet says in a comment that ``gonio.models`` must register it (``model.to_mitsuba``
    does) in the process that loads the scene.
    """
    lines, d = _bsdf_lines(model_name, options, params, bsdf_id, None)
    return "\n".join(lines) + "\n", d


def mitsuba_document(model_name: str, options: dict | None, params: dict, *, bsdf_id: str = "gonio_fit") -> str:
    """A fitted model as a Mitsuba 3 XML file of its own: ``mitsuba.load_file`` loads it (a BSDF)
    and ``<include filename="..."/>`` inserts it into a scene (``<ref id=bsdf_id/>``).

    Parameters are those of :func:`mitsuba_snippet`; the root ``<bsdf>`` carries
    ``version="3.0.0"`` (:data:`MITSUBA_XML_VERSION`), after an XML declaration.

    Returns
    -------
    str
        The file's text (UTF-8).
    """
    lines, _ = _bsdf_lines(model_name, options, params, bsdf_id, MITSUBA_XML_VERSION)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + "\n".join(lines) + "\n"
