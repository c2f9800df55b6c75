"""softras_cl.checks: the input checks shared by every layer."""
import numpy as np
import pytest

from softras_cl.checks import check_finite


@pytest.mark.parametrize("values, ok", [([1e308, 1e308], True), ([np.inf, -np.inf], False),
                                        ([1.0, np.nan], False), ([-np.inf, 1.0], False), ([], True)])
def test_finite_check_by_sum_falls_back_when_the_sum_overflows(values, ok):
    """check_finite sums first: a sum that overflows (finite values) must still pass, and
    Infs that cancel into NaN must still fail."""
    arr = np.array(values, np.float64)
    if ok:
        check_finite("grad_rgb", arr)
    else:
        with pytest.raises(ValueError, match="grad_rgb contains NaN or Inf"):
            check_finite("grad_rgb", arr)
