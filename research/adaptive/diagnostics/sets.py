"""The six selection sets of rounds 6-8 (presets whose test graphs the diagnostics read)."""

SETS = {
    "s1": ["paper_20th"],
    "s2": ["vary_sharp", "vary_blurry", "vary_objects"],
    "s3": ["vary_wide", "vary_dense", "vary_noisy"],
    "s4": ["vary_few", "vary_heavy", "vary_mid"],
    "s5": ["vary_loose", "vary_tight", "vary_mixed"],
    "s6": ["vary_sparse", "vary_busy", "vary_calm"],
}
