"""Reports of results: plots (matplotlib, headless) and tables (rich)."""
