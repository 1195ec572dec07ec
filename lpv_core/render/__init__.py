"""The renderer: rasterised G-buffer and shadow maps, direct light, the LPV lookup per pixel, EXR."""
