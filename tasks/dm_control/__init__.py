"""MJX ports of DM Control suite tasks."""
