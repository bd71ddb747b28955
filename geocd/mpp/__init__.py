"""Building extraction and change from two images: a multitemporal marked point process of rectangles
optimised by multiple birth and death (Benedek, Descombes & Zerubia), with geocd's height and 3-D change
terms. See ``docs/mpp.md``."""
