"""The GL compute backend (moderngl compute shaders) of the propagation and the lookup."""
