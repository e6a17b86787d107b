

def test_shard_samples_store_the_converted_cameras(tmp_path):
    from physgm.data.shards import ShardRecord, asset_to_sample

    _cameras_json(tmp_path, "opengl", GL_C2W)
    (tmp_path / "physical.json").write_text(json.dumps({"material": "Jelly", "E": 1e4, "nu": 0.45}))
    sample = asset_to_sample(str(tmp_path))
    record = ShardRecord({**sample, "id": "a"})
    np.testing.assert_allclose(record.c2w[0].numpy(), CV_C2W, atol=1e-7)
    assert record.physical.material == "jelly"
