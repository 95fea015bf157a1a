"""Methods as plug-ins: one module each, listed in `registry` (the only list of names)."""
