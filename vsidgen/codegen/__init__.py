"""Codegen stage: SymbolicModel -> readable JAX module ``generated/<name>.py``.

The jinja2 template ``templates/model.py.j2`` is package data of this package.

Public API::

    build(spec_paths, *, out_dir, force) -> [BuildResult]
    build_model(symbolic, *, out_dir, force) -> BuildResult
    generate(symbolic, *, spec_path) -> str
    is_up_to_date(symbolic, module_path) -> bool
"""

from .jaxmodule import BuildResult, build, build_model, display_path, generate, is_up_to_date

__all__ = ["BuildResult", "build", "build_model", "display_path", "generate", "is_up_to_date"]
