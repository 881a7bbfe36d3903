"""The wizard's pages, in order: rig, fringes, acquire, phase maps, calibrate, compare, export."""
