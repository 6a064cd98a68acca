"""A fitted model as Mitsuba 3 XML: a snippet to paste into a scene, or a file of its own.

The two forms differ only in the root's ``version`` attribute, which Mitsuba 3 needs on the
root of every file it loads and refuses elsewhere: :func:`mitsuba_snippet` (no ``version``, to
paste inside a ``<scene>``) and :func:`mitsuba_document` (the ``<bsdf>`` as a file's root,
``version="3.0.0"``; ``<include>`` it and ``<ref id="gonio_fit"/>``).

``plugins="native"`` writes what a plain Mitsuba loads (:mod:`.native`: the model's native twin, or
the closest native family fitted to it, its error in a comment); ``plugins="gonio"`` gonio's own
Python plugin where the model has one (exact; the loading process must import gonio).
:func:`write_mitsuba_document` and :func:`write_mitsuba_dict` read what they wrote back and compare
it with the dict. Values are XML-escaped (``quoteattr``); comments never hold ``--``.
"""

# Mitsuba 3's XML parser (src/core/xml.cpp, "Scene format" in its documentation) requires
# `version` on the root element of every file it loads (mitsuba.load_file and <include> alike)
# and refuses it on any other element ("unexpected attribute"). MITSUBA_XML_VERSION is the
# scene-format version of Mitsuba 3, which 3.x parsers read without upgrading it.

from __future__ import annotations

import json
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

import gonio.models as gm
from gonio.core.channels import CHANNELS
from gonio.fitting.formats.readback import expect, written

__all__ = ["MITSUBA_XML_VERSION", "PLUGINS", "mitsuba_document", "mitsuba_snippet", "write_mitsuba_document",
           "write_mitsuba_dict"]

#: What a model without a native plugin is written as: the closest native family, or gonio's plugin.
PLUGINS = ("native", "gonio")

#: The ``version`` of Mitsuba 3's scene format written on a file's root element.
MITSUBA_XML_VERSION = "3.0.0"


def _fmt_float(v) -> str:
    return repr(float(v))


def _rgb(key, value, indent) -> str:
    v = np.broadcast_to(np.asarray(value, dtype=np.float64), (CHANNELS,))
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
            elif kind == "spectrum":        # a spectral fit's (wavelength nm, value) pairs: Mitsuba's "l:v, ..."
                pairs = ", ".join(f"{float(w):g}:{_fmt_float(v)}" for w, v in value["value"])
                lines.append(f'{indent}<spectrum name={quoteattr(key)} value="{pairs}"/>')
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
        elif isinstance(value, (list, tuple, np.ndarray)) and np.size(value) == CHANNELS:
            lines.append(_rgb(key, value, indent))
        else:
            raise TypeError(f"cannot write Mitsuba property {key!r} of type {type(value).__name__} as XML")
    return lines


def _comment(text: str) -> str:
    return "<!-- " + text.replace("--", "- -") + " -->"


def _bsdf_lines(model_name, options, params, bsdf_id, version, plugins="gonio"):
    """(XML lines, the Mitsuba dict, a one-line note on what was written: None when it is the model itself)."""
    if plugins not in PLUGINS:
        raise ValueError(f"plugins={plugins!r}: use one of {', '.join(PLUGINS)}")
    model = gm.get(model_name, **(options or {}))
    head = f"gonio fit: model {model.name}, options {dict(model.options)}; f_r in sr^-1."
    if plugins == "native":
        from gonio.fitting.formats.native import native_bsdf

        nb = native_bsdf(model_name, options, params)
        d, note = nb.mitsuba, nb.note()
        if not nb.exact:
            head += f" Written as {nb.name} {nb.options} {dict((k, np.asarray(v).tolist()) for k, v in nb.params.items())}."
    else:
        d = model.to_mitsuba(params)
        note = f"model {model.name} as Mitsuba's {d['type']} plugin"
    kind = str(d["type"])
    lines = [_comment(head + " Exterior index 1 (ext_ior) where the model has one."), _comment(note + ".")]
    if plugins == "native" and nb.exact or plugins == "gonio" and not kind.startswith("gonio_"):
        note = None                     # the file is the model itself: nothing to tell
    if kind.startswith("gonio_"):
        note += " (gonio's Python plugin: the loading process must import gonio)"
        lines.append(_comment(f"'{kind}' is a Python BSDF: call gonio.models.get({model.name!r}).to_mitsuba(params)"
                              " (which runs mitsuba.register_bsdf) before loading this scene."))
    turn = _tangent_lines(model, params, bsdf_id)
    if turn:    # said on the command line too: a scene that ignores it shows the brushing at 0 deg
        t = float(model.tangent_deg(params))
        frame = (f"the BSDF is in the sample's tangent frame: turn the shape {t:.2f} deg about its normal "
                 "(gonio.models.mitsuba.tangent_to_world; --to mitsuba-xml writes the <shape>)")
        note = f"{note}; {frame}" if note else frame
    lines.extend(turn)
    root = f" version={quoteattr(version)}" if version else ""
    lines.append(f"<bsdf type={quoteattr(kind)} id={quoteattr(bsdf_id)}{root}>")
    lines.extend(_xml_lines(d, "    "))
    lines.append("</bsdf>")
    return lines, d, note


def _tangent_lines(model, params, bsdf_id) -> list[str]:
    """For a model whose BSDF is written in a turned tangent frame (``model.tangent_deg``:
    anisotropic roughconductor), the frame as comments: a Mitsuba BSDF holds none (its tangent
    is the shape's dp/du), so the shape's ``to_world`` turns about its normal, as the
    ``<shape>`` given (gonio.models.mitsuba.tangent_to_world does the same in Python)."""
    t = float(getattr(model, "tangent_deg", lambda p: 0.0)(params))
    if t == 0.0:
        return []
    shape = (f'<shape type="rectangle"><transform name="to_world"><rotate z="1" angle="{t!r}"/></transform>'
             f"<ref id={quoteattr(bsdf_id)}/></shape>")
    return [_comment(f"tangent frame: alpha_u acts along the shape's dp/du; the sample's tangent lies {t!r} deg "
                     "from the holder's x axis, so turn the shape about its normal by tangent_deg (before "
                     "its own to_world) as in:"), _comment(shape)]


def mitsuba_snippet(model_name: str, options: dict | None, params: dict, *, bsdf_id: str = "gonio_fit",
                    plugins: str = "gonio"):
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
    plugins : {"gonio", "native"}
        For a model without a native plugin: gonio's Python plugin (exact) or the closest
        native family fitted to it (:mod:`.native`; a plain Mitsuba loads it).

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
    lines, d, _ = _bsdf_lines(model_name, options, params, bsdf_id, None, plugins)
    return "\n".join(lines) + "\n", d


def mitsuba_document(model_name: str, options: dict | None, params: dict, *, bsdf_id: str = "gonio_fit",
                     plugins: str = "gonio") -> str:
    """A fitted model as a Mitsuba 3 XML file of its own: ``mitsuba.load_file`` loads it (a BSDF)
    and ``<include filename="..."/>`` inserts it into a scene (``<ref id=bsdf_id/>``).

    Parameters are those of :func:`mitsuba_snippet`; the root ``<bsdf>`` carries
    ``version="3.0.0"`` (:data:`MITSUBA_XML_VERSION`), after an XML declaration.

    Returns
    -------
    str
        The file's text (UTF-8).
    """
    return _document(model_name, options, params, bsdf_id, plugins)[0]


def _document(model_name, options, params, bsdf_id, plugins):
    lines, d, note = _bsdf_lines(model_name, options, params, bsdf_id, MITSUBA_XML_VERSION, plugins)
    return '<?xml version="1.0" encoding="utf-8"?>\n' + "\n".join(lines) + "\n", d, note


def _flat(d: dict, prefix: str = "") -> dict:
    """``{path: value}`` of a Mitsuba dict's properties, nested plugins by path; numbers as float
    tuples (an ``rgb`` of one value as its channels)."""
    out = {}
    for key, value in d.items():
        if key in ("type", "id"):
            continue
        path = f"{prefix}{key}"
        if isinstance(value, dict) and value.get("type") == "spectrum" and isinstance(value.get("value"), (list, tuple)):
            out[path] = tuple(float(x) for pair in value["value"] for x in pair)       # (nm, value) pairs
        elif isinstance(value, dict) and value.get("type") in ("rgb", "spectrum") and "value" in value:
            out[path] = tuple(float(x) for x in np.broadcast_to(np.asarray(value["value"], float),
                                                                 (CHANNELS,) if value["type"] == "rgb" else ()).ravel())
        elif isinstance(value, dict):
            out[path] = ("plugin", str(value.get("type")))
            out.update(_flat(value, path + "."))
        elif isinstance(value, (bool, np.bool_, str)):
            out[path] = (str(value).lower() if isinstance(value, (bool, np.bool_)) else value,)
        elif np.size(value) == CHANNELS and not np.isscalar(value):
            out[path] = tuple(float(x) for x in np.asarray(value, float).ravel())
        else:
            out[path] = (float(value),)
    return out


def _flat_xml(elem, prefix: str = "") -> dict:
    """:func:`_flat` of a parsed ``<bsdf>`` element."""
    out = {}
    for child in elem:
        path = f"{prefix}{child.get('name')}"
        if child.tag in ("rgb", "spectrum", "float", "integer"):
            out[path] = tuple(float(x) for item in child.get("value").split(",") for x in item.split(":"))
        elif child.tag in ("boolean", "string"):
            out[path] = (child.get("value"),)
        else:
            out[path] = ("plugin", child.get("type"))
            out.update(_flat_xml(child, path + "."))
    return out


def write_mitsuba_document(path, model_name: str, options: dict | None, params: dict, *,
                           plugins: str = "native", bsdf_id: str = "gonio_fit") -> str | None:
    """Write :func:`mitsuba_document` to ``path``, read it back and compare it with the BSDF dict.

    Returns
    -------
    str or None
        One line saying what was written instead of the model (the native family fitted to it
        and its error, or gonio's plugin); None when the file is the model's own plugin.

    Raises
    ------
    ExportError
        When the file read back does not hold every property of the dict, each with its value
        (nothing is written then).
    """
    import xml.etree.ElementTree as ET

    text, d, note = _document(model_name, options, params, bsdf_id, plugins)

    def write(tmp):
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)

    def check(tmps):
        root = ET.parse(tmps[Path(path)]).getroot()
        expect("Mitsuba XML root", f"<bsdf type={d['type']!r}>", f"<{root.tag} type={root.get('type')!r}>")
        want, got = _flat(d), _flat_xml(root)
        expect("Mitsuba XML properties", len(want), len(got))
        for key, value in want.items():
            expect(f"Mitsuba XML property {key}", value, got.get(key))

    written({Path(path): write}, check)
    return note


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):        # a spectrum's (nm, value) pairs stay pairs
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return [_jsonable(v) for v in np.asarray(value, dtype=object).ravel()] if np.ndim(value) else _jsonable(value.item())
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer, int)):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return float(value)
    return value


def write_mitsuba_dict(path, model_name: str, options: dict | None, params: dict, *,
                       plugins: str = "native") -> str | None:
    """Write the model's ``mitsuba.load_dict`` dict as JSON, read it back and compare (as
    :func:`write_mitsuba_document`); return the one-line note."""
    _, d, note = _bsdf_lines(model_name, options, params, "gonio_fit", None, plugins)
    doc = _jsonable(d)
    text = json.dumps(doc, indent=2, allow_nan=False) + "\n"

    def write(tmp):
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)

    def check(tmps):
        with open(tmps[Path(path)], encoding="utf-8") as fh:
            back = json.load(fh)
        expect("Mitsuba dict properties", len(_flat(doc)), len(_flat(back)))
        expect("Mitsuba dict read back", doc, back)

    written({Path(path): write}, check)
    return note
