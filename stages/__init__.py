"""Stages of hybrid-iamp: pure cores plus thin bus bindings (see STYLE.md)."""
