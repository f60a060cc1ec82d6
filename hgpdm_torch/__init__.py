"""hgpdm-torch."""
