"""models subpackage of hgpdm_torch."""
