"""The application: what ties values, logic and I/O together for the commands."""
