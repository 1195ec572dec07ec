"""Multi-layer OpenEXR files in Blender's layout (numpy + OpenEXR only, never bpy).

Blender 5.0 (Cycles, ``media_type = 'MULTI_LAYER_IMAGE'``) writes one EXR *part* per render
pass, the part named ``"<layer>.<pass>"`` and its channels ``"<layer>.<pass>.<id>"``, e.g.
``ViewLayer.Combined.R/G/B/A``, ``ViewLayer.Diffuse Direct.R/G/B``, ``ViewLayer.Depth.Z``,
``ViewLayer.Normal.X/Y/Z``, ``ViewLayer.Vector.X/Y/Z/W``, ``ViewLayer.UV.U/V/A``, all float32,
ZIP, top row first. :func:`write_multilayer` writes exactly that layout, so Blender, its
compositor and :func:`read_multilayer` read our files and Cycles' files alike.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Mapping
from pathlib import Path

import numpy as np

try:  # OpenEXR >= 3.3 (the pybind11 API with File/Part)
    import OpenEXR
except ImportError as exc:  # pragma: no cover - exercised only where OpenEXR is missing
    raise ImportError("lpv_core.render.exr needs the OpenEXR package (pip install OpenEXR)") from exc

__all__ = [
    "ExrError",
    "channel_ids",
    "channel_names",
    "read_multilayer",
    "write_multilayer",
]

# Attribute Blender writes into multi-layer files (kept for fidelity; harmless elsewhere).
_BLENDER_MULTICHANNEL = "Blender V2.55.1 and newer"

# Channel ids Blender uses for passes that are not colours.
_PASS_CHANNEL_IDS = {
    "Depth": "Z",
    "Mist": "Z",
    "Normal": "XYZ",
    "Position": "XYZ",
    "Vector": "XYZW",
    "UV": "UVA",
}
_DEFAULT_CHANNEL_IDS = {1: "X", 3: "RGB", 4: "RGBA"}

# Sort order of channel ids inside one pass (anything unknown goes last, alphabetically).
_CHANNEL_ORDER = {"R": 0, "G": 1, "B": 2, "A": 3, "X": 0, "Y": 1, "Z": 2, "W": 3, "U": 0, "V": 1}


class ExrError(ValueError):
    """An EXR file could not be read or does not hold what was asked for."""


def channel_ids(pass_name: str, n_channels: int) -> str:
    """Blender's channel ids (one letter each) for a pass with ``n_channels`` channels."""
    ids = _PASS_CHANNEL_IDS.get(pass_name)
    if ids is not None and len(ids) == n_channels:
        return ids
    try:
        return _DEFAULT_CHANNEL_IDS[n_channels]
    except KeyError:
        raise ValueError(
            f"pass {pass_name!r}: {n_channels} channels; expected 1, 3 or 4"
        ) from None


def _as_hwc(name: str, arr: np.ndarray) -> np.ndarray:
    a = np.asarray(arr)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4):
        raise ValueError(f"pass {name!r}: expected an (H, W, C) array with C in 1/3/4, "
                         f"got shape {np.shape(arr)}")
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"pass {name!r}: empty image {a.shape}")
    return a.astype(np.float32, copy=False)


def write_multilayer(
    path: str | os.PathLike, passes: Mapping[str, np.ndarray], layer: str = "ViewLayer"
) -> None:
    """Write ``{pass name: (H, W, C) array}`` as a Blender-style multi-layer float32 EXR.

    Rows are top-first (as a viewer shows the image). The file appears atomically: it is
    written to a hidden temporary file in the same folder and then renamed over ``path``.
    """
    if not passes:
        raise ValueError("write_multilayer: no passes given")
    if "." in layer or any("." in p for p in passes):
        raise ValueError("layer and pass names must not contain '.' (Blender splits on it)")
    arrays = {name: _as_hwc(name, arr) for name, arr in passes.items()}
    shapes = {a.shape[:2] for a in arrays.values()}
    if len(shapes) != 1:
        raise ValueError(f"all passes must have the same (H, W); got {sorted(shapes)}")

    parts = []
    for i, (name, a) in enumerate(arrays.items()):
        prefix = f"{layer}.{name}"
        ids = channel_ids(name, a.shape[2])
        channels = {
            f"{prefix}.{cid}": np.ascontiguousarray(a[:, :, k]) for k, cid in enumerate(ids)
        }
        header = {
            "compression": OpenEXR.ZIP_COMPRESSION,
            "type": OpenEXR.scanlineimage,
            "lineOrder": OpenEXR.INCREASING_Y,
        }
        if i == 0:
            header["BlenderMultiChannel"] = _BLENDER_MULTICHANNEL
        parts.append(OpenEXR.Part(header, channels, prefix))

    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with OpenEXR.File(parts) as f:
            f.write(str(tmp))
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def _open(path: Path) -> OpenEXR.File:
    if not path.is_file():
        raise FileNotFoundError(f"EXR file not found: {path}")
    try:
        return OpenEXR.File(str(path), separate_channels=True)
    except Exception as exc:  # OpenEXR raises RuntimeError/ValueError on corrupt data
        raise ExrError(f"cannot read EXR file {path}: {exc}") from exc


def channel_names(path: str | os.PathLike) -> list[str]:
    """All channel names in an EXR file (every part), in file order."""
    path = Path(path)
    with _open(path) as f:
        return [name for part in f.parts for name in part.channels]


def _split(name: str) -> tuple[str, str, str]:
    """Split a channel name into (layer, pass, channel id) the way Blender does."""
    tokens = name.split(".")
    if len(tokens) == 1:  # plain single-layer file: R, G, B, A (and Z)
        chan = tokens[0]
        if chan in ("R", "G", "B", "A"):
            return "", "Combined", chan
        return "", "Depth" if chan == "Z" else chan, chan
    if len(tokens) == 2:
        return "", tokens[0], tokens[1]
    return ".".join(tokens[:-2]), tokens[-2], tokens[-1]


def _window(header: Mapping) -> tuple[int, int, int, int] | None:
    win = header.get("dataWindow")
    if win is None:
        return None
    (x0, y0), (x1, y1) = (tuple(int(v) for v in w) for w in win)
    return x0, y0, x1, y1


def read_multilayer(
    path: str | os.PathLike, layer: str | None = None
) -> dict[str, np.ndarray]:
    """Read a multi-layer EXR into ``{pass name: (H, W, C) float32}``, rows top-first.

    Pass names are Blender's ("Combined", "Diffuse Direct", "Diffuse Indirect", "Diffuse
    Color", "Depth", ...); channels come in RGBA / XYZW / UVA order. ``layer`` picks a view
    layer when the file holds several (default: the only one). A plain RGBA EXR reads as
    "Combined". Raises FileNotFoundError or :class:`ExrError` naming the file.
    """
    path = Path(path)
    with _open(path) as f:
        # {layer: {pass: {channel id: 2-D array}}}
        layers: dict[str, dict[str, dict[str, np.ndarray]]] = {}
        display = None
        for part in f.parts:
            header = part.header
            disp = header.get("displayWindow")
            if display is None and disp is not None:
                display = _window({"dataWindow": disp})
            data_win = _window(header)
            for name, channel in part.channels.items():
                lay, pas, cid = _split(name)
                pix = np.asarray(channel.pixels)
                if pix.ndim != 2:
                    raise ExrError(f"{path}: channel {name!r} is not a flat image "
                                   f"(shape {pix.shape}); deep/sub-sampled EXR unsupported")
                pix = pix.astype(np.float32)  # a copy: owns its memory after the file closes
                if display is not None and data_win is not None and data_win != display:
                    pix = _to_display(pix, data_win, display)
                layers.setdefault(lay, {}).setdefault(pas, {})[cid] = pix

    if not layers:
        raise ExrError(f"{path}: no channels")
    if layer is None:
        if len(layers) > 1:
            raise ExrError(f"{path}: several view layers {sorted(layers)}; pass layer=...")
        chosen = next(iter(layers.values()))
    else:
        if layer not in layers:
            raise ExrError(f"{path}: no view layer {layer!r}; found {sorted(layers)}")
        chosen = layers[layer]

    out: dict[str, np.ndarray] = {}
    for pas, chans in chosen.items():
        order = sorted(chans, key=lambda c: (_CHANNEL_ORDER.get(c, 99), c))
        shapes = {chans[c].shape for c in order}
        if len(shapes) != 1:
            raise ExrError(f"{path}: pass {pas!r} has channels of different sizes {shapes}")
        out[pas] = np.stack([chans[c] for c in order], axis=-1)
    return out


def _to_display(
    pix: np.ndarray, data_win: tuple[int, int, int, int], display: tuple[int, int, int, int]
) -> np.ndarray:
    """Place a data-window image inside the display window (zeros outside)."""
    dx0, dy0, dx1, dy1 = display
    full = np.zeros((dy1 - dy0 + 1, dx1 - dx0 + 1), np.float32)
    x0, y0, x1, y1 = data_win
    # Intersect, in display coordinates.
    ix0, iy0, ix1, iy1 = max(x0, dx0), max(y0, dy0), min(x1, dx1), min(y1, dy1)
    if ix0 <= ix1 and iy0 <= iy1:
        full[iy0 - dy0 : iy1 - dy0 + 1, ix0 - dx0 : ix1 - dx0 + 1] = pix[
            iy0 - y0 : iy1 - y0 + 1, ix0 - x0 : ix1 - x0 + 1
        ]
    return full
