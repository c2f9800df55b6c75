"""Independent references to check softras-cl against: a trimesh/Embree ray cast and
Mitsuba 3 (optional extra `validate`), and the comparison metrics and figure."""
