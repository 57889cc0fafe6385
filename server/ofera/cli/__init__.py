"""The `ofera` command line."""
