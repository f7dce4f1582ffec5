"""Every deprecated name of the package, each working with a ``DeprecationWarning`` until
:data:`REMOVED_IN`:

* the method names ``ngpt`` and ``ngpt-nograd`` (:data:`METHOD_ALIASES`, registered as
  aliases of :data:`gdpt.methods.METHODS`);
* the study method names ``gdpt+ngpt`` and ``pt+ngpt-nograd`` (:data:`EVAL_METHOD_ALIASES`,
  registered as aliases of :data:`gdpt.study.methods.EVAL_METHODS`, and read under their
  current names from an earlier study's ``results.json`` by
  :func:`gdpt.study.results.read_results`);
* the environment variable ``GDPT_NGPT_MODEL`` (:data:`MODEL_ENV_DEPRECATED`, read by
  :func:`gdpt.checkpoints.model_path`);
* the ``oidn`` method's ``backend="pyoidn"``, now ``"native"``
  (:data:`OIDN_IMPLEMENTATION_ALIASES`, read by :func:`gdpt.oidn.oidn_denoise`);
* the module ``gdpt.denoise`` (re-exports of :mod:`gdpt.methods`, :mod:`gdpt.checkpoints`,
  :mod:`gdpt.adapters` and :mod:`gdpt.oidn`) and its function
  ``gdpt.denoise.reconstruct``, the former name of :func:`gdpt.reconstruct_image`; they stay in
  ``gdpt/denoise.py``, which imports :mod:`gdpt.methods` (this module is imported by it).

This module imports nothing from :mod:`gdpt`, so every layer may use it.
"""

from __future__ import annotations

import warnings

#: The release that removes the names listed above.
REMOVED_IN = "0.2.0"

#: Deprecated method name -> its current name.
METHOD_ALIASES = {"ngpt": "oidn-grad", "ngpt-nograd": "oidn-tuned"}

#: Deprecated study method name -> its current name (the method names of
#: :data:`METHOD_ALIASES` behind their sampler, ``gdpt+`` or ``pt+``).
EVAL_METHOD_ALIASES = {"gdpt+ngpt": "gdpt+oidn-grad", "pt+ngpt-nograd": "pt+oidn-tuned"}

#: Deprecated name of the environment variable ``GDPT_OIDN_GRAD_MODEL``
#: (:data:`gdpt.checkpoints.MODEL_ENV`).
MODEL_ENV_DEPRECATED = "GDPT_NGPT_MODEL"

#: Deprecated implementation name of the ``oidn`` method (``backend=``) -> its current name.
OIDN_IMPLEMENTATION_ALIASES = {"pyoidn": "native"}


def warn(old: str, instead: str, *, stacklevel: int = 3) -> None:
    """Warn that ``old`` is deprecated (``DeprecationWarning``: "``old`` is deprecated;
    ``instead`` (removed in :data:`REMOVED_IN`)")."""
    warnings.warn(
        f"{old} is deprecated; {instead} (removed in {REMOVED_IN})",
        DeprecationWarning,
        stacklevel=stacklevel,
    )
