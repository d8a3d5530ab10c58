"""The A/B comparison of our integrator against stock Mitsuba: the render harness, `compare()`, image metrics, the
two-step verdict, the report page and Embree ground truth."""
