import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture(scope="session")
def variant():
    """Mitsuba's ``llvm_ad_rgb`` variant with the gdpt plugins registered."""
    import gdpt

    return gdpt.set_variant("llvm_ad_rgb")
