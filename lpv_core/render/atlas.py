"""Many orthographic depth maps in one draw call and one readback: instance i of the uploaded
triangles is drawn with view i into tile i of one float32 atlas, clipped to it (the World's
64 or 128 directions; one pass per map of four RGBA32F targets cost ~1.4 ms each on llvmpipe).
Each tile holds -(view @ p).z of the nearest occluder, inf where nothing was hit, the same
float32 expression render/direct.render_shadow_map takes from the positions it reads back;
the nearest is kept by blending with GL_MIN, not by a depth test: the least of those float32
values exactly (a fixed-point depth buffer kept a farther one where surfaces meet), and no
depth buffer to clear and test."""

from __future__ import annotations

import numpy as np

from .raster import HASHED_ALPHA

# HASHED 0 draws a scene with no coverage below 1 and no alpha map (Rasterizer.hashed) without
# the coverage's inputs and hash: about half the maps' cost on llvmpipe (docs/decisions.md)
VERTEX_SHADER = """
uniform vec2 tiles;  // tiles per row, rows
in vec3 in_pos;
in float in_recv;  // raster.VERTEX_SHADER's code: bit 2, casts no shadow (left out)
#if HASHED
in float in_alpha;  // coverage (raster.HASHED_ALPHA)
in vec2 in_uv;
in float in_layer;
flat out float v_alpha;
flat out float v_layer;
out vec2 v_uv;
#endif
in vec4 c0;  // columns of the instance's view_proj (on origin-relative positions)
in vec4 c1;
in vec4 c2;
in vec4 c3;
in vec4 row;  // its view's third row (on origin-relative positions)
in vec2 tile;  // its tile (column, row from the bottom)
out float v_depth;
out float gl_ClipDistance[4];
void main() {
    vec4 c = mat4(c0, c1, c2, c3) * vec4(in_pos, 1.0);  // orthographic: w = 1
    c.y = -c.y;  // the map's top row first in GL's bottom-up rows: read back as they lie
    gl_ClipDistance[0] = c.w - c.x;
    gl_ClipDistance[1] = c.w + c.x;
    gl_ClipDistance[2] = c.w - c.y;
    gl_ClipDistance[3] = c.w + c.y;
    v_depth = -(dot(row.xyz, in_pos) + row.w);
    c.xy = ((c.xy + c.w) * 0.5 + tile * c.w) / tiles * 2.0 - c.w;
#if HASHED
    v_alpha = in_alpha;
    v_layer = in_layer;
    v_uv = in_uv;
#endif
    gl_Position = (int(in_recv + 0.5) & 4) != 0 ? vec4(0.0, 0.0, 2.0, 1.0) : c;
}
"""

FRAGMENT_SHADER = """
#if HASHED
""" + HASHED_ALPHA + """
#endif
in float v_depth;
out float o_depth;
void main() {
#if HASHED
    if (hashed_out()) discard;
#endif
    o_depth = v_depth;
}
"""

# the vertex buffer's fields each variant reads (raster.VERTEX_FLOATS a vertex)
_LAYOUTS = {True: ("3f 36x 1f 1f 4x 2f 1f", "in_pos", "in_recv", "in_alpha", "in_uv",
                   "in_layer"),
            False: ("3f 36x 1f 20x", "in_pos", "in_recv")}


def _header(hashed: bool) -> str:
    return f"#version 330\n#define HASHED {int(hashed)}\n"


_CLIP_DISTANCE0 = 0x3000  # GL_CLIP_DISTANCE0


class DepthAtlas:
    """The atlas pass of one Rasterizer (its context, triangles and origin)."""

    def __init__(self, raster):
        self.raster = raster
        self.programs = {h: raster.ctx.program(vertex_shader=_header(h) + VERTEX_SHADER,
                                                fragment_shader=_header(h) + FRAGMENT_SHADER)
                         for h in (True, False)}
        self._fbo: tuple | None = None  # (size, framebuffer)

    def render(self, views: list, resolution: int) -> np.ndarray:
        """Depth maps (K, R, R) float32, rows top-first like Rasterizer.read's, of the
        orthographic ``views`` (scene.lights.LightView) at ``resolution``, inf where empty."""
        import moderngl

        raster, ctx, k = self.raster, self.raster.ctx, len(views)
        # columns of tiles as tall as the driver allows, each read into its place in the stack
        tallest = min(ctx.info["GL_MAX_VIEWPORT_DIMS"][1], ctx.info["GL_MAX_TEXTURE_SIZE"],
                      ctx.info["GL_MAX_RENDERBUFFER_SIZE"])
        ny = max(1, min(k, tallest // resolution))
        nx = -(-k // ny)
        size = (nx * resolution, ny * resolution)
        held = (0, 0) if self._fbo is None else self._fbo[0]
        if size[0] > held[0] or size[1] > held[1]:  # grown only: the GI's and the pixels' maps
            big = (max(size[0], held[0]), max(size[1], held[1]))  # share it (a new one: 80 ms)
            if self._fbo is not None:
                self._fbo[1].release()
            self._fbo = (big, ctx.framebuffer(
                color_attachments=[ctx.texture(big, 1, dtype="f4")]))
        fbo = self._fbo[1]
        fbo.use()
        fbo.viewport = (0, 0, *size)
        fbo.clear(np.inf, viewport=fbo.viewport)
        vbo = raster._vbo
        if vbo is not None and k:
            shift = np.eye(4)
            shift[:3, 3] = raster.origin
            inst = np.empty((k, 22), np.float32)
            for i, v in enumerate(views):
                view = np.asarray(v.view, np.float64) @ shift
                inst[i, :16] = (np.asarray(v.projection, np.float64) @ view).T.reshape(16)
                inst[i, 16:20] = view[2]
                inst[i, 20:] = (i // ny, i % ny)
            buf = ctx.buffer(inst.tobytes())
            hashed = raster.hashed
            program = self.programs[hashed]
            vao = ctx.vertex_array(program, [(vbo, *_LAYOUTS[hashed]),
                                             (buf, "4f 4f 4f 4f 4f 2f/i", "c0", "c1", "c2",
                                              "c3", "row", "tile")])
            program["tiles"].value = (float(nx), float(ny))
            if hashed:
                program["seed"].value, program["samples"].value = 0, 1
                if raster._alpha_maps is not None:
                    from .raster import ALPHA_MAP_UNIT

                    raster._alpha_maps.use(location=ALPHA_MAP_UNIT)
                    program["alpha_maps"].value = ALPHA_MAP_UNIT
            ctx.disable(moderngl.DEPTH_TEST)
            ctx.disable(moderngl.CULL_FACE)
            ctx.enable(moderngl.BLEND)
            ctx.blend_equation = moderngl.MIN  # (the blend factors do not apply to MIN)
            for i in range(4):
                ctx.enable_direct(_CLIP_DISTANCE0 + i)
            vao.render(instances=k)
            for i in range(4):
                ctx.disable_direct(_CLIP_DISTANCE0 + i)
            ctx.blend_equation = moderngl.FUNC_ADD
            ctx.disable(moderngl.BLEND)
            vao.release()
            buf.release()
        out = np.empty((nx * ny, resolution, resolution), np.float32)
        for col in range(nx):
            fbo.read_into(out, (col * resolution, 0, resolution, size[1]), 1, dtype="f4",
                          write_offset=col * ny * resolution * resolution * 4)
        return out[:k]

    def release(self) -> None:
        if self._fbo is not None:
            self._fbo[1].release()
            self._fbo = None
        for program in self.programs.values():
            program.release()
