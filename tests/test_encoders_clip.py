"""CLIP through ONNX: a tiny random-weight transformers CLIPModel is exported by the real exporter and
loaded by the real loader; its embeddings must equal the torch model's."""
import json

import numpy as np
import pytest

from dualnerf.encoders import EncoderError, load_encoder

WORDS = ["a", "photo", "of", "snow", "make", "it", "look", "like", "winter", "campsite", "tent", "the",
         "turn", "into", "autumn", "scene"]
SPECIAL = ["<|startoftext|>", "<|endoftext|>"]    # CLIP's BOS/EOS; EOS doubles as pad, like OpenAI CLIP


def build_tiny_tokenizer():
    """A word-level `tokenizers` tokenizer with CLIP-style special tokens (EOS has the highest id)."""
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, processors

    vocab = {"[UNK]": 0, "<|startoftext|>": 1}
    for word in WORDS:
        vocab[word] = len(vocab)
    vocab["<|endoftext|>"] = len(vocab)
    tok = Tokenizer(models.WordLevel(vocab=vocab, unk_token="[UNK]"))
    tok.normalizer = normalizers.Lowercase()
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.post_processor = processors.TemplateProcessing(
        single="<|startoftext|> $A <|endoftext|>",
        special_tokens=[("<|startoftext|>", 1), ("<|endoftext|>", vocab["<|endoftext|>"])])
    return tok, vocab


def build_tiny_clip_source(folder, seed=0, image_size=32, context_length=12):
    """Save a tiny random CLIPModel + fast tokenizer + image processor config like a hub repo."""
    import torch
    from transformers import CLIPConfig, CLIPImageProcessor, CLIPModel, PreTrainedTokenizerFast

    tok, vocab = build_tiny_tokenizer()
    eos = vocab["<|endoftext|>"]
    text = {"vocab_size": len(vocab), "hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 2,
                "num_attention_heads": 2, "max_position_embeddings": context_length, "bos_token_id": 1,
                "eos_token_id": eos, "pad_token_id": eos}
    vision = {"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 2, "num_attention_heads": 2,
                  "image_size": image_size, "patch_size": 8}
    torch.manual_seed(seed)
    model = CLIPModel(CLIPConfig(text_config=text, vision_config=vision, projection_dim=16)).eval()
    model.save_pretrained(folder)
    fast = PreTrainedTokenizerFast(tokenizer_object=tok, bos_token="<|startoftext|>", eos_token="<|endoftext|>",
                                   pad_token="<|endoftext|>", unk_token="[UNK]")
    fast.save_pretrained(folder)
    CLIPImageProcessor(size={"shortest_edge": image_size}, crop_size={"height": image_size, "width": image_size},
                       image_mean=[0.5, 0.4, 0.3], image_std=[0.2, 0.25, 0.3]).save_pretrained(folder)
    return model


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    from dualnerf.encoders.clip_export import export_clip

    root = tmp_path_factory.mktemp("clip")
    model = build_tiny_clip_source(root / "hf")
    export_clip(str(root / "hf"), root / "onnx", log=lambda *_: None)
    return model, root


def test_onnx_embeddings_equal_torch(exported):
    import torch

    model, root = exported
    encoder = load_encoder("clip", root / "onnx")
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, size=(3, 40, 48, 3), dtype=np.uint8)   # not square: resize + crop run
    from dualnerf.encoders.clip_onnx import preprocess_images

    pixels = preprocess_images(images, encoder.preprocess)
    assert pixels.shape == (3, 3, 32, 32)
    with torch.no_grad():
        expected = model(pixel_values=torch.from_numpy(pixels), input_ids=torch.tensor([[1, 2]])).image_embeds
    got = encoder.encode_images(images)
    np.testing.assert_allclose(got, expected.numpy(), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)

    texts = ["make it look like snow", "a photo of the campsite", "winter"]
    ids, mask = encoder.tokenize(texts)
    with torch.no_grad():
        expected = model(input_ids=torch.from_numpy(ids), attention_mask=torch.from_numpy(mask),
                         pixel_values=torch.zeros(1, 3, 32, 32)).text_embeds
    np.testing.assert_allclose(encoder.encode_texts(texts), expected.numpy(), atol=1e-5)
    # different texts give different embeddings (the EOS pooling position follows the text length)
    emb = encoder.encode_texts(texts)
    assert np.abs(emb[0] - emb[2]).max() > 1e-3


def test_tokenizer_and_preprocessing_match_transformers(exported):
    from transformers import AutoTokenizer, CLIPImageProcessor

    _, root = exported
    encoder = load_encoder("clip", root / "onnx")
    hf = AutoTokenizer.from_pretrained(root / "hf")
    texts = ["Make it look like SNOW", "a " * 30]                 # second one must be truncated, EOS kept
    ids, mask = encoder.tokenize(texts)
    ref = hf(texts, padding="max_length", max_length=12, truncation=True)
    np.testing.assert_array_equal(ids, np.array(ref["input_ids"]))
    np.testing.assert_array_equal(mask, np.array(ref["attention_mask"]))
    assert ids[1, -1] == hf.eos_token_id and ids.shape == (2, 12)
    # preprocessing: same resize/crop/normalisation as transformers' processor (PIL vs torch bicubic differ
    # slightly on noise, so compare a smooth image)
    yy, xx = np.mgrid[0:64, 0:80]
    smooth = np.stack([yy / 63, xx / 79, (yy + xx) / 142], axis=-1)
    image = (smooth * 255).astype(np.uint8)[None]
    ref_pixels = CLIPImageProcessor.from_pretrained(root / "hf")(list(image), return_tensors="np")["pixel_values"]
    from dualnerf.encoders.clip_onnx import preprocess_images

    np.testing.assert_allclose(preprocess_images(image, encoder.preprocess), ref_pixels, atol=0.08)
    assert encoder.identity["kind"] == "clip" and len(encoder.identity["sha256"]) == 64


def test_corrupt_or_missing_files_are_clear_errors(exported, tmp_path):
    import shutil

    _, root = exported
    copy = tmp_path / "copy"
    shutil.copytree(root / "onnx", copy)
    with open(copy / "text_encoder.onnx", "ab") as handle:
        handle.write(b"x")
    with pytest.raises(EncoderError, match="text_encoder.onnx.*sha256"):
        load_encoder("clip", copy)
    (copy / "manifest.json").unlink()
    with pytest.raises(EncoderError, match="manifest.json is missing"):
        load_encoder("clip", copy)
    with pytest.raises(EncoderError, match="needs a model folder"):
        load_encoder("clip", None)
    with pytest.raises(EncoderError, match="not empty"):
        from dualnerf.encoders.clip_export import export_clip

        export_clip(str(root / "hf"), root / "onnx")
    manifest = json.loads((root / "onnx" / "manifest.json").read_text())
    assert set(manifest["files"]) == {"image_encoder.onnx", "text_encoder.onnx", "tokenizer.json",
                                      "preprocess.json"}


def test_export_command_through_the_cli(tmp_path, capsys):
    from experiments.cli import main

    build_tiny_clip_source(tmp_path / "hf", seed=1)
    assert main(["models", "export-clip", "--from", str(tmp_path / "hf"), "--out", str(tmp_path / "m"),
                 "--check"]) == 0
    assert "check: max |onnx - torch|" in capsys.readouterr().out
    assert load_encoder("clip", tmp_path / "m").identity["model"] == str(tmp_path / "hf")
    # a bad source is a user error (exit 2, message naming what to pass)
    assert main(["models", "export-clip", "--from", str(tmp_path / "nothing"), "--out", str(tmp_path / "n")]) == 2
    assert "could not load a transformers CLIPModel" in capsys.readouterr().err
