"""Compiled twins of the stages (numba, through runtime.jit).

``kernels/<stage>.py`` holds, under the same name and signature, the compiled version of each
public function of the stage module that has one; the stage keeps the numpy reference and picks
the twin with one switch at the top of the function::

    if jit.enabled():
        return _compiled.<function>(...)

where ``_compiled`` is the stage's ``from .kernels import <stage> as _compiled``. A kernel module
never imports its stage (no import cycle); ``@jit.kernel`` functions that other compiled code
calls are its entry points (``*_kernel``) and their helpers. The tests hold every twin to its
reference, bit for bit where the stage says so (tests/test_jit_*.py).
"""
