"""The command line, parameter sweeps and figures."""
