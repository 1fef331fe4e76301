"""Device side of svs_torch: the SVS emulator and hardware notes."""
