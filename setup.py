"""The one part of evtk's build that pyproject.toml cannot state: the optional C extension ``evtk._ckernels``.

It is built where a C compiler is present; where the build fails (no compiler, no Python headers) the
installation goes on without it and evtk does its work in Python and numpy instead (``evtk._native``).
"""

import os

from setuptools import Extension, setup

# the C maths library, which the timing solve's exp and log come from (part of the C library on Windows and macOS)
LIBM = ["m"] if os.name == "posix" else []
setup(ext_modules=[Extension("evtk._ckernels", ["evtk/_ckernels.c"], libraries=LIBM, optional=True)])
