"""ms_drake: robot mechanical search in Drake.

See README.md for the two commands (demo, tests) and ../shared/DESIGN.md for the architecture.
"""

__version__ = "0.1.0"
