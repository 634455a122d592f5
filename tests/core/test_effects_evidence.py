"""The evidence sentences say which way the misfit moved."""

from app.core.effects import misfit_change
from app.core.effects.compressibility import evidence


def test_the_misfit_change_reads_the_right_way():
    assert misfit_change(0.89, 0.83) == "falls from 0.89 to 0.83 px"
    # a candidate that fits worse must not read "falls from 0.89 to 1.59"
    assert misfit_change(0.89, 1.59) == "rises from 0.89 to 1.59 px"
    assert misfit_change(0.891, 0.889) == "stays at 0.89 px"
    assert evidence(0.40, 0.49, 0.9, 1.2).endswith("the displacement misfit rises from 0.90 to 1.20 px")
