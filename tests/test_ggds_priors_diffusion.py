"""DiffusersPrior with tiny randomly initialised components saved to a temp dir (no downloads)."""
import json
import shutil

import pytest
import torch

from lsd3d_usd.errors import InputError
from lsd3d_usd.conditioning.light import PriorEnv
from lsd3d_usd.ggds.priors.synthetic import street_gbuffer

diffusers = pytest.importorskip("diffusers")
transformers = pytest.importorskip("transformers")


def tiny_clip_tokenizer(d):
    """A minimal CLIP BPE vocabulary: single characters (+ end-of-word forms), a few merges."""
    chars = list("abcdefghijklmnopqrstuvwxyz0123456789.,!?'-")
    vocab = {}
    for c in chars:
        vocab[c] = len(vocab)
    for c in chars:
        vocab[c + "</w>"] = len(vocab)
    merges = [("s", "t"), ("r", "e"), ("e", "t</w>")]
    for a, b in merges:
        vocab[a + b] = len(vocab)
    vocab["<|startoftext|>"] = len(vocab)
    vocab["<|endoftext|>"] = len(vocab)
    d.mkdir(parents=True)
    (d / "vocab.json").write_text(json.dumps(vocab))
    (d / "merges.txt").write_text("#version: 0.2\n" + "\n".join(f"{a} {b}" for a, b in merges) + "\n")
    tok = transformers.CLIPTokenizer(str(d / "vocab.json"), str(d / "merges.txt"), model_max_length=16)
    tok.save_pretrained(d)
    return len(vocab)


@pytest.fixture(scope="module")
def tiny_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny_sd")
    torch.manual_seed(0)
    n_vocab = tiny_clip_tokenizer(root / "tokenizer")
    unet = diffusers.UNet2DConditionModel(
        sample_size=8, in_channels=4, out_channels=4, layers_per_block=1, block_out_channels=(32, 64),
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"), up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=32, attention_head_dim=8, norm_num_groups=32)
    unet.save_pretrained(root / "unet")
    vae = diffusers.AutoencoderKL(in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(32, 64),
                                  down_block_types=("DownEncoderBlock2D",) * 2,
                                  up_block_types=("UpDecoderBlock2D",) * 2, layers_per_block=1, norm_num_groups=32)
    vae.save_pretrained(root / "vae")
    te = transformers.CLIPTextModel(transformers.CLIPTextConfig(
        vocab_size=n_vocab, hidden_size=32, intermediate_size=37, num_hidden_layers=2, num_attention_heads=4,
        max_position_embeddings=16, bos_token_id=n_vocab - 2, eos_token_id=n_vocab - 1, pad_token_id=n_vocab - 1))
    te.save_pretrained(root / "text_encoder")
    diffusers.DDIMScheduler(beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012).save_pretrained(root / "scheduler")
    cn = diffusers.ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(16, 32))
    with torch.no_grad():  # ControlNet's zero convolutions start at 0: give them weights so it acts
        for prm in cn.parameters():
            if float(prm.abs().sum()) == 0.0:
                prm.normal_(0.0, 0.05)
    cn.save_pretrained(root / "controlnet")
    return root, root / "controlnet"


@pytest.fixture(scope="module")
def prior(tiny_dirs):
    from lsd3d_usd.ggds.priors.diffusion import DiffusersPrior
    root, cn = tiny_dirs
    return DiffusersPrior.from_pretrained(root, controlnet_dir=cn, guidance_scale=3.0)


@pytest.fixture(scope="module")
def view():
    gb = street_gbuffer(32, 32)
    x = torch.rand(32, 32, 3, generator=torch.Generator().manual_seed(0))
    return x, gb


def test_loads_offline_and_shapes(prior, view):
    import os
    assert os.environ.get("HF_HUB_OFFLINE") == "1"
    x, gb = view
    env = PriorEnv(prompt="a street", negative_prompt="blurry")
    y = prior.target(x, gb, env, 0.5, n_steps=2)
    assert y.shape == x.shape and y.dtype == torch.float32
    assert torch.isfinite(y).all() and float(y.min()) >= 0 and float(y.max()) <= 1
    assert prior.describe()["controlnet"] is True


def test_deterministic_per_seed(prior, view):
    x, gb = view
    env = PriorEnv(prompt="a street")
    a = prior.target(x, gb, env, 0.7, n_steps=2, seed=3)
    b = prior.target(x, gb, env, 0.7, n_steps=2, seed=3)
    assert torch.equal(a, b)


def test_t_to_zero_is_vae_reconstruction(prior, view):
    x, gb = view
    env = PriorEnv()
    y = prior.target(x, gb, env, 1e-4)
    rec = prior.decode(prior.encode(x), 32, 32)
    assert torch.allclose(y, rec, atol=1e-6)
    # a real level does change the latent (the UNet and ControlNet run)
    assert not torch.allclose(prior.target(x, gb, env, 0.9, n_steps=2), rec, atol=1e-4)


def test_controlnet_conditioning_matters(prior, view):
    x, gb = view
    env = PriorEnv(prompt="a street")
    gb2 = street_gbuffer(32, 32, eye=(0.0, 3.0, 6.0), target=(10.0, -3.0, 0.0))
    a = prior.target(x, gb, env, 0.8, n_steps=2)
    b = prior.target(x, gb2, env, 0.8, n_steps=2)
    assert not torch.allclose(a, b, atol=1e-5)


@pytest.mark.parametrize("remove,msg", [
    ("unet/config.json", "UNet"), ("vae", "VAE"), ("text_encoder/model.safetensors", "text encoder"),
    ("tokenizer/merges.txt+tokenizer/tokenizer.json", "tokenizer"), ("controlnet/diffusion_pytorch_model.safetensors", "ControlNet"),
])
def test_incomplete_directory_is_a_clear_error(tiny_dirs, tmp_path, remove, msg):
    from lsd3d_usd.ggds.priors.diffusion import DiffusersPrior
    root, _ = tiny_dirs
    copy = tmp_path / "m"
    shutil.copytree(root, copy)
    for r in remove.split("+"):
        p = copy / r
        assert p.exists(), f"fixture layout changed: {p}"
        shutil.rmtree(p) if p.is_dir() else p.unlink()
    with pytest.raises(InputError, match=msg):
        DiffusersPrior.from_pretrained(copy, controlnet_dir=copy / "controlnet")


def test_missing_dir_and_sdxl_refused(tmp_path):
    from lsd3d_usd.ggds.priors.diffusion import DiffusersPrior
    with pytest.raises(InputError, match="not found"):
        DiffusersPrior.from_pretrained(tmp_path / "nope")
    (tmp_path / "xl" / "text_encoder_2").mkdir(parents=True)
    with pytest.raises(InputError, match="SDXL"):
        DiffusersPrior.from_pretrained(tmp_path / "xl")
