"""``sp_plugins.stats``: how a paired difference is quoted in tables (the benches' and the docs' form)."""

from sp_plugins.stats import paired_difference


def test_a_paired_difference_is_quoted_as_mean_and_interval():
    # b - a = +2.0, +0.2: mean 1.10, sd 1.273, t(0.975, 1) = 12.706 -> half width 11.44
    assert paired_difference([10.0, 11.0], [12.0, 11.2]).text(2) == "+1.10 [-10.34, +12.54]"
    assert paired_difference([1.0, 2.0, 3.0], [1.5, 2.5, 3.6]).text(3) == "+0.533 [+0.390, +0.677]"
    assert paired_difference([1.0], [0.75]).text(2) == "-0.25"  # one pair: no interval to quote
