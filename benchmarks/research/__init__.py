"""One-off research: the GPU campaign and its helpers, the critical-event probe of α."""
