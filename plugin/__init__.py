"""layerbvh_mitsuba: the Mitsuba 3 side of layerbvh (Embree reference queries; scene adapter and integrator to come)."""
