"""Visual disk tracking (Yi et al. 2021, Sec. V-A): data, models, training."""
