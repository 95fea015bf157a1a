"""MJX ports of MetaWorld v3 tasks."""
