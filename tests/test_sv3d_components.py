"""SV3D's conditioning-frame encoder, temporal video decoder and OpenCLIP image tower, with TINY random
models written to one .safetensors file under the official prefixes and loaded through the real
builders: shapes, determinism, temporal mixing, chunked decoding, preprocessing, layout errors, and
the official key layout of the full-size models (read from shapes on the meta device)."""

from __future__ import annotations

from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from humanvdm_core.models import openclip_vision as clip  # noqa: E402
from humanvdm_core.models import sv3d_vae as vae  # noqa: E402
from humanvdm_core.models.checkpoint import CheckpointError, read_state_dict  # noqa: E402


@pytest.fixture(scope="module")
def tiny_file(tmp_path_factory) -> Path:
    from safetensors.torch import save_file

    sd = {}
    sd.update({vae.FIRST_STAGE_PREFIX + k: v for k, v in vae.tiny_video_decoder_state_dict(1).items()})
    sd.update({vae.COND_ENCODER_PREFIX + k: v for k, v in vae.tiny_cond_encoder_state_dict(2).items()})
    sd.update({clip.OPENCLIP_PREFIX + k: v for k, v in clip.tiny_state_dict(3).items()})
    path = tmp_path_factory.mktemp("sv3d") / "sv3d_tiny.safetensors"
    save_file(sd, str(path))
    return path


@pytest.fixture(scope="module")
def parts(tiny_file) -> dict:
    sd = read_state_dict(tiny_file, "SV3D", "nowhere")
    return {name: vae.strip_prefix(sd, prefix) for name, prefix in
            (("first_stage", vae.FIRST_STAGE_PREFIX), ("cond", vae.COND_ENCODER_PREFIX),
             ("clip", clip.OPENCLIP_PREFIX))}


def _meta_state_dict(module_factory) -> dict:
    with torch.device("meta"):
        return dict(module_factory().state_dict())


# ----------------------------------------------------------------------------- official layouts

def test_full_size_video_decoder_layout():
    sd = _meta_state_dict(lambda: vae.VideoFirstStage((128, 256, 512, 512), 2, 4, (3, 1, 1)))
    assert len(sd) == 266  # sgm VideoDecoder(ch 128, ch_mult [1,2,4,4], 2 res blocks, conv-only), all under decoder.
    expected = {"decoder.conv_in.weight": (512, 4, 3, 3),
                "decoder.mid.block_1.mix_factor": (1,),
                "decoder.mid.block_1.time_stack.in_layers.0.weight": (512,),
                "decoder.mid.block_2.time_stack.out_layers.3.weight": (512, 512, 3, 1, 1),
                "decoder.mid.attn_1.q.weight": (512, 512, 1, 1),
                "decoder.up.0.block.0.nin_shortcut.weight": (128, 256, 1, 1),
                "decoder.up.3.block.2.time_stack.in_layers.2.weight": (512, 512, 3, 1, 1),
                "decoder.up.1.upsample.conv.weight": (256, 256, 3, 3),
                "decoder.norm_out.weight": (128,),
                "decoder.conv_out.weight": (3, 128, 3, 3),
                "decoder.conv_out.time_mix_conv.weight": (3, 3, 3, 1, 1)}
    assert {k: tuple(sd[k].shape) for k in expected} == expected
    assert "decoder.up.0.upsample.conv.weight" not in sd
    assert vae.video_decoder_config(sd) == {"widths": (128, 256, 512, 512), "num_res_blocks": 2, "z_channels": 4,
                                            "video_kernel": (3, 1, 1), "attn": (False,) * 4}


def test_full_size_cond_encoder_layout():
    sd = _meta_state_dict(lambda: vae.CondFrameEncoder(128, (128, 256, 512, 512), 2, 4, 4))
    assert len(sd) == 108
    expected = {"encoder.conv_in.weight": (128, 3, 3, 3),
                "encoder.down.0.block.0.norm1.weight": (128,),
                "encoder.down.1.block.0.nin_shortcut.weight": (256, 128, 1, 1),
                "encoder.down.2.downsample.conv.weight": (512, 512, 3, 3),
                "encoder.mid.attn_1.q.weight": (512, 512, 1, 1),
                "encoder.conv_out.weight": (8, 512, 3, 3),
                "quant_conv.weight": (8, 8, 1, 1)}
    assert {k: tuple(sd[k].shape) for k in expected} == expected
    assert "encoder.down.3.downsample.conv.weight" not in sd
    cfg = vae.cond_encoder_config(sd)
    assert (cfg["ch"], cfg["widths"], cfg["num_res_blocks"], cfg["z_channels"], cfg["embed_dim"]) == \
        (128, (128, 256, 512, 512), 2, 4, 4)


def test_full_size_openclip_layout():
    sd = _meta_state_dict(clip.OpenCLIPImageEmbedder)  # ViT-H/14 defaults
    assert len(sd) == 392 and all(k.startswith("visual.") for k in sd)
    expected = {"visual.conv1.weight": (1280, 3, 14, 14), "visual.class_embedding": (1280,),
                "visual.positional_embedding": (257, 1280), "visual.ln_pre.weight": (1280,),
                "visual.transformer.resblocks.31.attn.in_proj_weight": (3840, 1280),
                "visual.transformer.resblocks.31.attn.out_proj.weight": (1280, 1280),
                "visual.transformer.resblocks.0.mlp.c_fc.weight": (5120, 1280),
                "visual.transformer.resblocks.0.mlp.c_proj.bias": (1280,),
                "visual.ln_post.bias": (1280,), "visual.proj": (1280, 1024)}
    assert {k: tuple(sd[k].shape) for k in expected} == expected
    assert clip.config_from_state_dict(sd) == {"image_size": 224, "patch_size": 14, "width": 1280, "layers": 32,
                                               "heads": 16, "mlp_width": 5120, "output_dim": 1024}


# ----------------------------------------------------------------------------- the tiny file

def test_tiny_file_has_the_official_prefixes(tiny_file, parts):
    sd = read_state_dict(tiny_file, "SV3D", "nowhere")
    assert sum(len(p) for p in parts.values()) == len(sd)
    assert all(k.startswith("decoder.") for k in parts["first_stage"])
    assert {k.split(".")[0] for k in parts["cond"]} == {"encoder", "quant_conv", "decoder", "post_quant_conv"}
    assert set(clip.TEXT_KEYS) - {"attn_mask"} <= set(parts["clip"])


def test_cond_encoder_shapes_and_determinism(parts):
    enc = vae.build_cond_encoder(parts["cond"], "tiny")
    assert enc.downsample_factor == 8 and enc.embed_dim == 4
    x = torch.rand(2, 3, 64, 48, generator=torch.Generator().manual_seed(0)) * 2 - 1
    z = enc.encode(x)
    assert z.shape == (2, 4, 8, 6) and torch.isfinite(z).all()
    assert torch.equal(z, vae.build_cond_encoder(parts["cond"]).encode(x))
    assert torch.allclose(z[1:], enc.encode(x[1:]), atol=1e-5)  # images are encoded independently
    other = vae.build_cond_encoder(vae.tiny_cond_encoder_state_dict(9)).encode(x)
    assert not torch.allclose(z, other)
    with pytest.raises(ValueError, match="multiples of 8"):
        enc.encode(x[..., :44])


def test_cond_encoder_ignores_only_the_image_decoder(parts):
    sd = {k: v for k, v in parts["cond"].items() if not k.startswith(("decoder.", "post_quant_conv."))}
    x = torch.zeros(1, 3, 16, 16)
    assert torch.equal(vae.build_cond_encoder(sd).encode(x), vae.build_cond_encoder(parts["cond"]).encode(x))


def test_video_decoder_shapes_range_and_temporal_mixing(parts):
    dec = vae.build_video_decoder(parts["first_stage"], "tiny")
    assert dec.downsample_factor == 8 and dec.z_channels == 4
    g = torch.Generator().manual_seed(0)
    z = torch.randn(2 * 3, 4, 4, 5, generator=g)  # 2 videos of 3 frames
    x = dec.decode(z, num_frames=3)
    assert x.shape == (6, 3, 32, 40) and x.min() >= -1.0 and x.max() <= 1.0
    assert torch.equal(x, vae.build_video_decoder(parts["first_stage"]).decode(z, 3))
    z2 = z.clone()
    z2[0] += torch.randn(z2[0].shape, generator=g)  # change frame 0 of video 0
    raw, raw2 = dec(z, 3), dec(z2, 3)
    assert (raw2[1] - raw[1]).abs().max() > 1e-4  # frame 1 of the same video sees frame 0 ...
    assert torch.equal(raw2[3:], raw[3:])  # ... the other video does not
    with pytest.raises(ValueError, match="whole number"):
        dec.decode(z, num_frames=4)


def test_image_decoder_of_sv3d_u_yaml_loads_and_decodes_frames_independently():
    """sv3d_u.yaml names sgm's plain image Decoder: no time_stack / time_mix_conv tensors."""
    sd = vae.tiny_video_decoder_state_dict(2, video=False)
    assert not any("time_" in k or "mix_factor" in k for k in sd)
    dec = vae.build_video_decoder(sd, "tiny image decoder")
    z = torch.randn(3, 4, 4, 4, generator=torch.Generator().manual_seed(2))
    x = dec.decode(z, num_frames=3)
    assert x.shape == (3, 3, 32, 32)
    assert torch.allclose(x[1:2], dec.decode(z[1:2], num_frames=1), atol=1e-5)  # no mixing across frames


def test_decode_chunked(parts):
    dec = vae.build_video_decoder(parts["first_stage"])
    z = torch.randn(5, 4, 4, 4, generator=torch.Generator().manual_seed(1))
    whole = dec.decode(z, num_frames=5)
    assert torch.equal(vae.decode_chunked(dec, z, 5), whole)
    assert torch.equal(vae.decode_chunked(dec, z, 8), whole)
    chunked = vae.decode_chunked(dec, z, 2)  # calls of 2, 2 and 1 frames
    assert chunked.shape == whole.shape
    assert torch.equal(chunked[:2], dec.decode(z[:2], 2)) and torch.equal(chunked[4:], dec.decode(z[4:], 1))
    assert not torch.equal(chunked, whole)  # the temporal layers see different neighbours
    with pytest.raises(ValueError):
        vae.decode_chunked(dec, z, 0)


def test_fp16_checkpoint_loads_as_float32(parts):
    half = {k: v.half() for k, v in parts["first_stage"].items()}
    dec = vae.build_video_decoder(half)
    assert all(p.dtype == torch.float32 for p in dec.parameters())


def test_layout_errors_name_the_keys(parts):
    sd = dict(parts["first_stage"])
    del sd["decoder.up.1.block.0.time_stack.out_layers.3.weight"]
    sd["decoder.up.1.block.0.extra.weight"] = torch.zeros(1)
    with pytest.raises(CheckpointError) as e:
        vae.build_video_decoder(sd, "bad.safetensors")
    msg = str(e.value)
    assert "bad.safetensors" in msg and "missing keys: decoder.up.1.block.0.time_stack.out_layers.3.weight" in msg
    assert "unexpected keys: decoder.up.1.block.0.extra.weight" in msg

    with pytest.raises(CheckpointError, match="missing keys: decoder.conv_out.time_mix_conv.weight"):
        vae.build_video_decoder({k: v for k, v in parts["first_stage"].items() if "time_mix_conv" not in k})
    with pytest.raises(CheckpointError, match="missing keys: encoder.conv_in.weight"):
        vae.build_cond_encoder(parts["first_stage"])

    cond = dict(parts["cond"], **{"encoder.mid.attn_1.extra": torch.zeros(1)})
    del cond["quant_conv.bias"]
    with pytest.raises(CheckpointError, match=r"missing keys: quant_conv.bias; unexpected keys: encoder.mid.attn_1.extra"):
        vae.build_cond_encoder(cond)

    cl = dict(parts["clip"], **{"visual.ls_1.gamma": torch.zeros(1), "transformer.resblocks.0.ln_1.weight":
                                torch.zeros(1)})
    del cl["visual.ln_post.weight"]
    with pytest.raises(CheckpointError) as e:
        clip.build_image_embedder(cl, "clip.bin")
    msg = str(e.value)
    assert "missing keys: visual.ln_post.weight" in msg
    assert "transformer.resblocks.0.ln_1.weight" in msg and "visual.ls_1.gamma" in msg

    shapes = dict(parts["clip"], **{"visual.ln_pre.bias": torch.zeros(3)})
    with pytest.raises(CheckpointError, match="shape mismatches: visual.ln_pre.bias"):
        clip.build_image_embedder(shapes)


def test_clip_embedding_and_preprocessing(parts):
    model = clip.build_image_embedder(parts["clip"], "tiny")
    assert model.image_size == 224 and model.output_dim == 1024
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 224, 224, generator=g) * 2 - 1
    e = model.embed(x)
    assert e.shape == (2, 1024) and torch.isfinite(e).all()
    assert torch.equal(e, clip.build_image_embedder(parts["clip"]).embed(x))
    # at 224² nothing is resized: the tower sees exactly the CLIP-normalised image
    mean, std = torch.tensor(clip.CLIP_MEAN).view(1, 3, 1, 1), torch.tensor(clip.CLIP_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        direct = model.visual(((x + 1) / 2 - mean) / std)
    assert torch.allclose(e, direct, atol=1e-5)

    # every input size is brought to 224²: a uniform colour embeds the same at any resolution
    colour = torch.tensor([0.3, -0.2, 0.7]).view(1, 3, 1, 1)
    flat = [model.embed(colour.expand(1, 3, h, w).contiguous()) for h, w in ((224, 224), (64, 64), (300, 200))]
    assert all(torch.allclose(flat[0], f, atol=1e-4) for f in flat[1:])

    # a smooth image at 448² embeds (almost) like the same image at 224²; another image does not
    def smooth(n: int) -> torch.Tensor:
        u = torch.linspace(0, 1, n)
        yy, xx = torch.meshgrid(u, u, indexing="ij")
        return torch.stack([torch.sin(2 * xx + yy), torch.cos(3 * yy) * xx, xx * yy * 2 - 1])[None]

    e224, e448 = model.embed(smooth(224)), model.embed(smooth(448))
    e_other = model.embed(smooth(224).flip(-1))
    assert (e448 - e224).norm() < 0.1 * (e_other - e224).norm()


def test_resize_antialias():
    def board(n: int) -> torch.Tensor:  # a +-1 checkerboard: all energy at the Nyquist frequency
        return ((torch.arange(n)[None, :] + torch.arange(n)[:, None]) % 2 * 2.0 - 1.0).expand(1, 3, n, n)

    aliased = torch.nn.functional.interpolate(board(896), size=(224, 224), mode="bicubic", align_corners=True)
    assert aliased.std() > 0.4  # a plain resize aliases the pattern into a visible one ...
    assert clip.resize_antialias(board(896), (224, 224)).abs().max() < 1e-3  # ... the blur (sigma 1.5) removes it
    half = clip.resize_antialias(board(448), (224, 224))  # kornia's sigma 0.5, 3 taps at factor 2: damped only
    assert half.shape == (1, 3, 224, 224) and 0.2 < half.abs().max() < 0.4
    x = torch.rand(1, 3, 224, 224)
    assert clip.resize_antialias(x, (224, 224)) is x
    up = clip.resize_antialias(x[..., :100, :100], (224, 224))  # upscaling: no blur, corners kept
    assert torch.allclose(up[..., 0, 0], x[..., 0, 0]) and torch.allclose(up[..., -1, -1], x[..., 99, 99])


def test_clip_text_keys_are_ignored_by_name(parts):
    visual_only = {k: v for k, v in parts["clip"].items() if k.startswith("visual.")}
    x = torch.zeros(1, 3, 224, 224)
    assert torch.equal(clip.build_image_embedder(visual_only).embed(x), clip.build_image_embedder(parts["clip"]).embed(x))
    with_mask = dict(parts["clip"], attn_mask=torch.zeros(8, 8))
    clip.build_image_embedder(with_mask)  # attn_mask: tolerated by name


def test_tiny_state_dicts_are_seeded():
    a, b, c = vae.tiny_video_decoder_state_dict(4), vae.tiny_video_decoder_state_dict(4), vae.tiny_video_decoder_state_dict(5)
    assert a.keys() == c.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a["decoder.conv_in.weight"], c["decoder.conv_in.weight"])
    s1, s2 = clip.tiny_state_dict(1), clip.tiny_state_dict(1)
    assert all(torch.equal(s1[k], s2[k]) for k in s1)
    assert clip.tiny_state_dict(1, output_dim=64)["visual.proj"].shape == (160, 64)
