"""Prefect flows and the `wonderverse` CLI."""
