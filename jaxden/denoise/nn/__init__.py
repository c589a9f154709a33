"""Flax linen modules for jaxden's denoisers, used only through pure ``init``/``apply``."""
