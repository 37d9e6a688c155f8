"""Camera conventions and conversions (torch)."""
