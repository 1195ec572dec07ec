"""Compiled twins of the stages (numba, through runtime.jit).

``kernels/<stage>.py`` holds, under the same name, the compiled version of each stage function
that has one; the stage keeps the numpy reference. The stage prepares its inputs once (the
conversions, checks and empty cases both paths share), then picks the twin with one switch::

    if jit.enabled():
        return _compiled.<function>(...)

so the twin takes the arguments as given or as prepared, and never repeats that preparation.

where ``_compiled`` is the stage's ``from .kernels import <stage> as _compiled``. A kernel module
never imports its stage (no import cycle); ``@jit.kernel`` functions that other compiled code
calls are its entry points (``*_kernel``) and their helpers. The tests hold every twin to its
reference, bit for bit where the stage says so (tests/test_jit_*.py).
"""
