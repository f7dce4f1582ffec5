"""The deprecated module ``gdpt.denoise``: it warns on import, names its removal release, and
re-exports the moved names unchanged; its ``reconstruct`` warns and is
``gdpt.reconstruct_image``; the study's deprecated method names are the method aliases behind
their sampler. The only tests that import ``gdpt.denoise`` (the others use the current names)."""

from __future__ import annotations

import subprocess
import sys
import warnings

import pytest
import torch

from gdpt import checkpoints, deprecated, methods, oidn


def _denoise():
    """The module ``gdpt.denoise``, imported without its warning (checked on its own below)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from gdpt import denoise
    return denoise


def test_importing_gdpt_denoise_warns_with_its_removal_release():
    code = (
        "import warnings\n"
        "with warnings.catch_warnings(record=True) as caught:\n"
        "    warnings.simplefilter('always')\n"
        "    import gdpt.denoise\n"
        "print([str(w.message) for w in caught if w.category is DeprecationWarning])"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], check=True, capture_output=True, text=True
    )
    assert "gdpt.denoise is deprecated" in result.stdout
    assert f"removed in {deprecated.REMOVED_IN}" in result.stdout


def test_gdpt_denoise_reexports_the_moved_names():
    denoise = _denoise()
    assert denoise.METHODS is methods.METHODS and denoise.Method is methods.Method
    assert denoise.reconstruct_image is methods.reconstruct_image
    assert denoise.register_checkpoint is methods.register_checkpoint
    assert denoise.model_path is checkpoints.model_path
    assert denoise.load_reconstructor is checkpoints.load_reconstructor
    assert denoise.MODEL_DIR == checkpoints.MODEL_DIR
    assert denoise.oidn_denoise is oidn.oidn_denoise and denoise.oidn_check is oidn.oidn_check
    assert set(deprecated.METHOD_ALIASES) <= set(methods.METHODS.aliases)


def test_deprecated_reconstruct_warns_and_returns_the_same(random_buffers):
    buffers = random_buffers(names=("primal", "dx", "dy"))
    message = r"gdpt\.denoise\.reconstruct is deprecated; use gdpt\.reconstruct_image"
    with pytest.warns(DeprecationWarning, match=message):
        old = _denoise().reconstruct(buffers, "l2", alpha=0.5)
    assert torch.equal(old, methods.reconstruct_image(buffers, "l2", alpha=0.5))


def test_study_aliases_are_the_method_aliases_behind_their_sampler():
    from gdpt.study.methods import EVAL_METHODS

    assert EVAL_METHODS.aliases == deprecated.EVAL_METHOD_ALIASES
    expected = {}
    for old, new in deprecated.METHOD_ALIASES.items():
        sampler = "gdpt" if methods.METHODS[new].gradients else "pt"
        expected[f"{sampler}+{old}"] = f"{sampler}+{new}"
    assert deprecated.EVAL_METHOD_ALIASES == expected
