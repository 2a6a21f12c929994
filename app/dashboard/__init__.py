"""The dashboard: server-rendered HTML with inline SVG plots drawn by matplotlib (offline)."""
