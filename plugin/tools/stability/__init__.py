"""The stability suite (numerically hard cases against Embree and stock), the command line under abuse, and
STABILITY.md."""
