"""Figures (matplotlib, Agg backend, no pyplot global state)."""
