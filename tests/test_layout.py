"""The tree's structure: no import cycle in lpv_core or lpv_addon (module-level and function-level
imports alike), the core never imports bpy or the add-on, shipped code never imports the
measurement tools, and the extension zip's Python stays within its line budget."""

from __future__ import annotations

import ast
import zipfile
from pathlib import Path

import pytest
from conftest import ROOT

PACKAGES = ("lpv_core", "lpv_addon")
# The extension zip's Python: 14,000 was the budget of the restructuring (13,721 lines then);
# the render engine, the shadow and RSM budgets, the input checks and the batch's output
# handling added about 1,500 lines of new behaviour; the light sources without an RSM (World,
# emitters), soft shadows and exact area lights, and the materials (Cycles' Diffuse Color
# rule, textures per point) about 3,300 more; the glossy bounce, Diffuse Color over each pixel's
# footprint and the view angle, the sky maps' atlas, an HDRI's sun and the soft shadows'
# depth pyramid about 1,300 more (19,755 then); images combined per texel, the mirror lobe's
# cut to its surface, the sky's direction sets per antialias sample, a batch's Ctrl-C held
# back while a frame is recorded, the World's and emitters' glossy bounce and the overlay's
# view-angle share about 380 more (20,137 then); point and spot lights' round emitters cut at
# the horizon, Cycles' object visibility (camera, shadow, diffuse, holdout, a collection's
# Holdout and Indirect Only) and Film > Transparent about 180 more (20,314 then); hashed alpha
# with per-texel alpha maps, translucency from the far side, light node trees, the view
# layer's Material Override and Environment filter, the Render Region, the passes' colour
# division, the soft shadows' form-factor weights and the World's diffuse-ray bake about 570
# more (20,886 then); tangent-space normal maps (the Normal Map node, Blender's tangents, the
# G-buffer's per-point normal) and the surfels' cut of huge triangles about 270 more (21,153
# then); the RSM's shading-normal gain, volume-only and closed emissive objects, portals,
# curve-like objects taken once and the Displacement note about 105 more (21,258 then); the
# sliver pixels' border samples through a cropped camera about 70 more (21,368 then); the
# shadow taps' occluder planes (thin walls' edges, cube seams) about 110 more (21,479 then); the
# soft taps' test of the occluder's own plane (a room's corners) about 110 more (21,591 then);
# the umbra's empty soft taps and the atlas's opaque variant about 20 more (21,610 then); the
# hard filter's crease test (walls standing on a ground) and the VPLs facing out of the LPV
# box about 85 more (21,695 then); the hard filter's taps that went round an occluder (a
# closed room's inner edges under the World) about 80 more (21,776 then); the lookup's
# corners in front of the receiver's own plane (a room of single faces) about 70 more (21,844
# then); the gaps of a room corner's cells and the faces lookups read as closed about 30 more
# (21,876 then); the soft filter's contact layer (the own texel's surface, resolved by the hard
# filter) about 32 more (21,912 then); the cascade count's hysteresis under its cap and the
# grid budget of the lights' kept grids (the 32^3 default) about 30 more (21,943 then); the
# contact light (the bounce from within a cell, render/contact.py, its compiled twin, the GI
# weights of the direct light) about 260 more (22,199 then); each cascade made whole for the
# receivers outside the finer ones (cascades.whole / reads, the overlay's box test per read,
# the bounces' reads) about 140 more (22,341 then); the contact light's exact form factor of
# each pixel's footprint (contact.patch_edges, the clipped contour integral per tap, in numpy
# and compiled) about 70 more (22,416 then); a sun's contact light gathered in the sun's own
# view (contact.sun_source / view_texels, gather_at receiver by receiver in numpy and
# compiled, the views kept over a frame's samples) and the finer cascades centred on the seen
# points their parent holds about 175 more (22,589 then). The cap catches duplicated code
# growing back; raise it only for new behaviour, by what that behaviour measures.
ZIP_PYTHON_LINES = 22_595


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    found = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            found[_module_name(path)] = path
    return found


def _resolve(module: str, is_package: bool, level: int, target: str | None) -> str:
    """The absolute module a relative import names (``from ..x import y`` in ``module``)."""
    base = module.split(".") if is_package else module.split(".")[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


def _imports(module: str, path: Path, modules: dict) -> set[str]:
    """Every module of the two packages that ``module`` imports, at any depth of its code.
    ``from a import b`` names the module a.b when that is a module, else a itself. The
    add-on's way to the core (``from .. import lpv_core``, outside the package) counts as
    lpv_core."""
    tree = ast.parse(path.read_text(), str(path))
    is_package = path.name == "__init__.py"
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                out.add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = _resolve(module, is_package, node.level, node.module)
            else:
                base = node.module or ""
            for alias in node.names:
                sub = f"{base}.{alias.name}" if base else alias.name
                out.add(sub if sub in modules or alias.name in PACKAGES else base)
    return {m if m in modules else m.split(".")[0] if m.split(".")[0] in PACKAGES else m
            for m in out if m.split(".")[0] in PACKAGES or m in PACKAGES}


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {m: _imports(m, p, modules) - {m} for m, p in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, comps, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return comps


def test_cycle_finder_finds_a_cycle() -> None:
    """The checker itself: a two-module loop and a three-module loop are reported."""
    graph = {"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"e"}, "e": {"c"}, "f": {"a"}}
    assert sorted(_cycles(graph)) == [["a", "b"], ["c", "d", "e"]]


def test_relative_imports_resolve() -> None:
    assert _resolve("lpv_core.render.deferred", False, 2, "engine") == "lpv_core.engine"
    assert _resolve("lpv_core.propagation", True, 1, "sweep") == "lpv_core.propagation.sweep"
    assert _resolve("lpv_addon._core", False, 2, None) == ""


def test_no_import_cycle() -> None:
    graph = _graph()
    assert len(graph) > 20  # both packages were walked
    assert _cycles(graph) == []


def test_core_imports_neither_bpy_nor_the_addon() -> None:
    for path in (ROOT / "lpv_core").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level
                     else [])
            for name in names:
                root = name.split(".")[0]
                assert root not in ("bpy", "lpv_addon", "tools", "mathutils", "gpu"), \
                    f"{path.relative_to(ROOT)} imports {name}"


def test_shipped_code_never_imports_the_tools() -> None:
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom) and not node.level:
                    assert (node.module or "").split(".")[0] != "tools", path
                elif isinstance(node, ast.Import):
                    assert all(a.name.split(".")[0] != "tools" for a in node.names), path


@pytest.fixture(scope="module")
def ext_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from tools.build_extension import build_all

    return build_all(tmp_path_factory.mktemp("layout_zip"), split_platforms=False)[0]


def test_zip_python_within_budget(ext_zip: Path) -> None:
    """The zip ships what Blender runs: its Python within the budget, no tools or tests."""
    with zipfile.ZipFile(ext_zip) as zf:
        names = zf.namelist()
        py = [n for n in names if n.endswith(".py")]
        lines = sum(zf.read(n).decode().count("\n") for n in py)
    assert not [n for n in names if n.split("/")[0] in ("tools", "tests", "docs")]
    assert {"lpv_core/engine.py", "lpv_addon/__init__.py", "__init__.py"} <= set(py)
    print(f"extension zip: {len(py)} Python files, {lines} lines")
    assert lines <= ZIP_PYTHON_LINES, f"{lines} lines of Python in the zip"
