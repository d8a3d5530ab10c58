"""The estimators we mirror, one file per stock integrator (path, direct, volpath, volpathmis, depth, ptracer, prb,
prb_basic, prbvolpath; media.py is the walk the volumetric ones share, replay.py the derivative half of a replayed
vertex): each samples, given its ray queries, and knows nothing of the render driver."""
