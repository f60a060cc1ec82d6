"""experiments subpackage of hgpdm_torch."""
