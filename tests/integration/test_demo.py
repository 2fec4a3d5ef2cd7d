import io

from sitl.demo import run_demo


def test_demo_flies_every_vehicle_to_completion(base_port):
    out = io.StringIO()
    assert run_demo(vehicles=2, speedup=40.0, base_port=base_port(2), out=out, timeout_s=60) == 0
    text = out.getvalue()
    assert "2/2 vehicles completed their missions" in text
    assert "vehicle 2: items reached [1, 2, 3, 4, 5, 6] -> landed" in text
