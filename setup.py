"""The one part of evtk's build that pyproject.toml cannot state: the optional C extension ``evtk._ckernels``.

It is built where a C compiler is present; where the build fails (no compiler, no Python headers) the
installation goes on without it and evtk does its work in Python and numpy instead (``evtk._native``).
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("evtk._ckernels", ["evtk/_ckernels.c"], optional=True)])
