"""The real InstructPix2Pix code path on a tiny randomly initialised diffusers pipeline built here."""
import numpy as np
import pytest

from dualnerf.editors import EditorError, load_editor
from dualnerf.editors.ip2p import (
    InstructPix2PixConfig,
    InstructPix2PixEditor,
    ddim_sample,
    ddim_timesteps,
    guided_noise,
)
from tests.test_encoders_clip import build_tiny_tokenizer


def build_tiny_ip2p(folder, seed=0):
    import torch
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, PreTrainedTokenizerFast

    torch.manual_seed(seed)
    UNet2DConditionModel(sample_size=8, in_channels=8, out_channels=4, layers_per_block=1,
                         block_out_channels=(32, 64), down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
                         up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"), cross_attention_dim=32,
                         attention_head_dim=4).save_pretrained(folder / "unet")
    AutoencoderKL(in_channels=3, out_channels=3, block_out_channels=(32, 64), latent_channels=4,
                  down_block_types=("DownEncoderBlock2D",) * 2, up_block_types=("UpDecoderBlock2D",) * 2,
                  ).save_pretrained(folder / "vae")
    tok, vocab = build_tiny_tokenizer()
    eos = vocab["<|endoftext|>"]
    CLIPTextModel(CLIPTextConfig(vocab_size=len(vocab), hidden_size=32, intermediate_size=64,
                                 num_hidden_layers=2, num_attention_heads=2, max_position_embeddings=12,
                                 bos_token_id=1, eos_token_id=eos, pad_token_id=eos)
                  ).save_pretrained(folder / "text_encoder")
    PreTrainedTokenizerFast(tokenizer_object=tok, bos_token="<|startoftext|>", eos_token="<|endoftext|>",
                            pad_token="<|endoftext|>", unk_token="[UNK]", model_max_length=12
                            ).save_pretrained(folder / "tokenizer")
    DDIMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", clip_sample=False,
                  set_alpha_to_one=False, steps_offset=1).save_pretrained(folder / "scheduler")


@pytest.fixture(scope="module")
def tiny_ip2p(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ip2p")
    build_tiny_ip2p(folder)
    return folder


def test_tiny_pipeline_runs_through_the_real_loader(tiny_ip2p):
    editor = load_editor("ip2p", instruction="make it snow", model=str(tiny_ip2p))
    assert isinstance(editor, InstructPix2PixEditor) and editor.identity["is_simulator"] is False
    rng = np.random.default_rng(0)
    render = rng.integers(0, 256, (20, 28, 3), dtype=np.uint8)          # not a multiple of the VAE factor
    original = rng.integers(0, 256, (20, 28, 3), dtype=np.uint8)
    a = editor.edit(render, original, "make it snow", seed=1, step=10)
    assert a.shape == (20, 28, 3) and a.dtype == np.float32 and 0 <= a.min() and a.max() <= 1
    low, high = 0.02 * 1000, 0.98 * 1000
    assert low <= editor.last_details["timestep"] <= high and editor.last_details["steps"] == 20
    np.testing.assert_array_equal(a, editor.edit(render, original, "make it snow", seed=1, step=10))
    b = editor.edit(render, original, "make it snow", seed=2, step=10)
    assert np.abs(a - b).max() > 1e-4
    # the original image conditions the result (through the UNet's extra 4 input channels)
    c = editor.edit(render, 255 - original, "make it snow", seed=1, step=10)
    assert np.abs(a - c).max() > 1e-4


def test_timestep_draws_cover_the_configured_range(tiny_ip2p):
    editor = InstructPix2PixEditor(tiny_ip2p, InstructPix2PixConfig(steps=1, lower_bound=0.3, upper_bound=0.4))
    img = np.zeros((8, 8, 3), np.uint8)
    ts = []
    for seed in range(30):
        editor.edit(img, img, "snow", seed=seed, step=0)
        ts.append(editor.last_details["timestep"])
    assert min(ts) >= 300 and max(ts) <= 400 and len(set(ts)) > 10


def test_guidance_and_ddim_closed_forms():
    import torch

    text, image, uncond = torch.tensor(3.0), torch.tensor(2.0), torch.tensor(1.0)
    assert guided_noise(text, image, uncond, 1.0, 1.0) == text               # both scales 1: plain text cond
    assert guided_noise(text, image, uncond, 0.0, 1.0) == image
    assert guided_noise(text, image, uncond, 7.5, 1.5) == 1.0 + 7.5 * 1.0 + 1.5 * 1.0
    schedule = ddim_timesteps(500, 20)
    assert len(schedule) == 20 and schedule[0] == (476, 451) and schedule[-1] == (1, -1)
    # with the exact noise as the prediction, deterministic DDIM recovers the clean latents
    alphas = torch.linspace(0.9999, 0.01, 1000, dtype=torch.float64)
    x0 = torch.randn(2, 4, 3, 3, dtype=torch.float64)
    noise = torch.randn_like(x0)
    t0 = schedule[0][0]
    xt = alphas[t0].sqrt() * x0 + (1 - alphas[t0]).sqrt() * noise
    out = ddim_sample(xt, lambda x, t: noise, schedule, alphas)
    torch.testing.assert_close(out, x0)


def test_missing_weights_is_a_clear_error(tmp_path):
    with pytest.raises(EditorError, match="lacks unet/.*timbrooks/instruct-pix2pix"):
        InstructPix2PixEditor(tmp_path / "nowhere")
