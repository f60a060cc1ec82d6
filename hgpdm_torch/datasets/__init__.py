"""datasets subpackage of hgpdm_torch."""
