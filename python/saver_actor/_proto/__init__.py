"""saver.proto's generated messages and stubs (python/generate_proto.sh makes them from
proto/saver.proto; tests/python/test_saver_actor.py checks that they are current)."""
