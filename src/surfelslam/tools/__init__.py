"""Command implementations (the only place, with ``viz/``, that prints, reads user files and plots).

Each module defines ``register(app)`` adding one typer command; :mod:`surfelslam.cli` lists them.
"""
