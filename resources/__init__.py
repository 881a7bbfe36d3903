"""Resources of PTP Studio (icons, default rigs, the stylesheet); installed as ``ptp_studio.resources``."""
