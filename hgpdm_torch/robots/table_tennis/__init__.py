"""table_tennis subpackage of hgpdm_torch."""
