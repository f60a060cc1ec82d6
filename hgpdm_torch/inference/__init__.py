"""inference subpackage of hgpdm_torch."""
