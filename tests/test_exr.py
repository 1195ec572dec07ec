"""lpv_core.render.exr: Blender-layout multi-layer EXR writer/reader (no bpy needed)."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

from lpv_core.render import exr

# Channel names exactly as Blender 5.0.1 / Cycles wrote them into a multi-layer EXR (one
# part per pass, file order within a part is alphabetical as OpenEXR requires).
BLENDER_CHANNELS = [
    "ViewLayer.Combined.A", "ViewLayer.Combined.B", "ViewLayer.Combined.G",
    "ViewLayer.Combined.R",
    "ViewLayer.Diffuse Direct.B", "ViewLayer.Diffuse Direct.G", "ViewLayer.Diffuse Direct.R",
    "ViewLayer.Diffuse Indirect.B", "ViewLayer.Diffuse Indirect.G",
    "ViewLayer.Diffuse Indirect.R",
    "ViewLayer.Diffuse Color.B", "ViewLayer.Diffuse Color.G", "ViewLayer.Diffuse Color.R",
]


def _passes(h: int = 5, w: int = 7, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "Combined": rng.normal(size=(h, w, 4)).astype(np.float32) * 100,
        "Diffuse Direct": rng.random((h, w, 3), np.float32) * 1e4,
        "Diffuse Indirect": rng.random((h, w, 3), np.float32) * 1e-4,
        "Diffuse Color": rng.random((h, w, 3), np.float32),
    }


def test_round_trip_exact(tmp_path):
    passes = _passes()
    passes["Depth"] = np.arange(35, dtype=np.float32).reshape(5, 7, 1)
    passes["Normal"] = np.ones((5, 7, 3), np.float32) * np.float32([0.0, 0.6, 0.8])
    path = tmp_path / "a.exr"
    exr.write_multilayer(path, passes)
    back = exr.read_multilayer(path)
    assert list(back) == list(passes)
    for name, arr in passes.items():
        assert back[name].dtype == np.float32
        assert back[name].shape == arr.shape
        np.testing.assert_array_equal(back[name], arr)


def test_channel_names_match_blender(tmp_path):
    path = tmp_path / "b.exr"
    exr.write_multilayer(path, _passes())
    assert exr.channel_names(path) == BLENDER_CHANNELS
    f = OpenEXR.File(str(path), header_only=True)
    assert [p.name() for p in f.parts] == [
        "ViewLayer.Combined", "ViewLayer.Diffuse Direct", "ViewLayer.Diffuse Indirect",
        "ViewLayer.Diffuse Color",
    ]
    assert f.parts[0].header["compression"] == OpenEXR.ZIP_COMPRESSION


def test_other_layer_and_channel_ids(tmp_path):
    path = tmp_path / "c.exr"
    one = np.zeros((2, 3, 1), np.float32)
    exr.write_multilayer(path, {"Depth": one, "Mist": one, "Vector": np.zeros((2, 3, 4)),
                                "AO": one}, layer="Layer2")
    assert exr.channel_names(path) == [
        "Layer2.Depth.Z", "Layer2.Mist.Z", "Layer2.Vector.W", "Layer2.Vector.X",
        "Layer2.Vector.Y", "Layer2.Vector.Z", "Layer2.AO.X",
    ]
    back = exr.read_multilayer(path, layer="Layer2")
    assert back["Vector"].shape == (2, 3, 4)


def test_rows_top_first_and_rgba_order(tmp_path):
    img = np.zeros((4, 6, 4), np.float32)
    img[0, :, 0] = 1.0  # top row red
    img[:, 0, 3] = 2.0  # left column alpha
    path = tmp_path / "d.exr"
    exr.write_multilayer(path, {"Combined": img})
    raw = OpenEXR.File(str(path), separate_channels=True).parts[0].channels
    # EXR's y axis points down: the first stored row (y = ymin) is the top of the image,
    # which is also how Blender stores renders (see test_reference's orientation check).
    np.testing.assert_array_equal(raw["ViewLayer.Combined.R"].pixels[0], np.ones(6))
    back = exr.read_multilayer(path)["Combined"]
    np.testing.assert_array_equal(back, img)


def test_reads_plain_rgba_and_2d_input(tmp_path):
    path = tmp_path / "plain.exr"
    rgba = np.random.default_rng(1).random((3, 4, 4), np.float32)
    chans = {c: np.ascontiguousarray(rgba[..., i]) for i, c in enumerate("RGBA")}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, chans) as f:
        f.write(str(path))
    np.testing.assert_array_equal(exr.read_multilayer(path)["Combined"], rgba)

    path2 = tmp_path / "mono.exr"
    exr.write_multilayer(path2, {"Depth": np.ones((3, 4))})
    assert exr.read_multilayer(path2)["Depth"].shape == (3, 4, 1)


def test_several_layers_need_a_choice(tmp_path):
    path = tmp_path / "two.exr"
    z = np.zeros((2, 2), np.float32)
    chans = {f"{lay}.Combined.{c}": z + k for k, lay in enumerate(("A", "B")) for c in "RGB"}
    with OpenEXR.File({}, chans) as f:
        f.write(str(path))
    with pytest.raises(exr.ExrError, match="several view layers"):
        exr.read_multilayer(path)
    assert exr.read_multilayer(path, layer="B")["Combined"].max() == 1.0
    with pytest.raises(exr.ExrError, match="no view layer 'C'"):
        exr.read_multilayer(path, layer="C")


def test_atomic_write_leaves_no_temp_files(tmp_path, monkeypatch):
    path = tmp_path / "atomic.exr"
    exr.write_multilayer(path, _passes(seed=1))
    exr.write_multilayer(path, _passes(seed=2))  # overwrite in place
    assert sorted(p.name for p in tmp_path.iterdir()) == ["atomic.exr"]
    np.testing.assert_array_equal(exr.read_multilayer(path)["Combined"],
                                  _passes(seed=2)["Combined"])

    # A failure before the rename keeps the old file intact and removes the temp file.
    def boom(src, dst):
        raise OSError("simulated crash before rename")

    monkeypatch.setattr(exr.os, "replace", boom)
    with pytest.raises(OSError, match="simulated"):
        exr.write_multilayer(path, _passes(seed=3))
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["atomic.exr"]
    np.testing.assert_array_equal(exr.read_multilayer(path)["Combined"],
                                  _passes(seed=2)["Combined"])


def test_errors_name_the_file(tmp_path):
    bad = tmp_path / "garbage.exr"
    bad.write_bytes(b"this is not an EXR file" * 10)
    with pytest.raises(exr.ExrError, match="garbage.exr"):
        exr.read_multilayer(bad)
    trunc = tmp_path / "truncated.exr"
    exr.write_multilayer(trunc, _passes(h=64, w=64))
    trunc.write_bytes(trunc.read_bytes()[:300])
    with pytest.raises(exr.ExrError, match="truncated.exr"):
        exr.read_multilayer(trunc)
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        exr.read_multilayer(tmp_path / "missing.exr")


@pytest.mark.parametrize(
    "passes",
    [
        {},
        {"Combined": np.zeros((2, 2, 2))},
        {"Combined": np.zeros((2, 2, 4)), "Diffuse Color": np.zeros((3, 2, 3))},
        {"Bad.Name": np.zeros((2, 2, 3))},
    ],
)
def test_rejects_bad_input(tmp_path, passes):
    with pytest.raises(ValueError):
        exr.write_multilayer(tmp_path / "x.exr", passes)
    assert list(tmp_path.iterdir()) == []
