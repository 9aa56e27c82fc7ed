"""Parameter identification: the fit as parts."""
