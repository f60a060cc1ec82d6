"""robots subpackage of hgpdm_torch."""
