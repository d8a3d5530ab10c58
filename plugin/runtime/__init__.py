"""What a Mitsuba scene needs at run time: the `layerbvh` integrator, the scene adapter, ray queries, feature plan,
settings, render statistics and ray recording."""
