"""Tools built on the runtime and the A/B comparison: converge, sweep, stability, the third-party table and the
benchmarks."""
