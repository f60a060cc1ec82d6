"""decision subpackage of hgpdm_torch."""
