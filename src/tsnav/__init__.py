"""tsnav: object navigation with the Two-Stage Reward Mechanism (TSRM) and Depth-Enhanced MAE (DE-MAE)."""

#: The one version number: pyproject.toml reads it (``[tool.setuptools.dynamic]``), model cards record it
#: (``tsnav_version``, :func:`tsnav.pipeline.release.pack`), CHANGELOG.md lists what each version changed.
__version__ = "0.2.0"
