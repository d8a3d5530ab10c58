"""The tests of the commands and tools built on the Mitsuba runtime: Mitsuba's variant."""
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
