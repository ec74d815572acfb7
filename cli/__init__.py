"""The rvnoise command line (typer). Installed as ``roadview_noise.cli``."""
