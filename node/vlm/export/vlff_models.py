"""PyTorch definitions of the two models vlff runs through OpenCV 4.6 DNN.

Both are written with plain ops so the ONNX graph holds only what OpenCV
4.6's importer runs correctly (see docs/vlm.md):
  * LayerNorm is decomposed ((x - mean) / sqrt(var + eps), no
    LayerNormalization op), and its gamma/beta are folded into the Linear
    that always follows it: OpenCV 4.6 fails on a per-channel Mul of a
    [1, N, D] tensor.
  * Attention is explicit MatMul/Softmax; the node turns layer fusion off.
Parameter names mirror the original checkpoints (openai/CLIP, LSeg/DPT) so
their state dicts load directly.
"""
import math

import torch
import torch.nn as nn
import torch.nn.functional as F



def init_params(module, g, norm_key):
    """Random weights of realistic scale (no checkpoints here): small biases,
    norm gains near 1 (named by norm_key), fan-in scaled matrices."""
    with torch.no_grad():
        for name, p in module.named_parameters():
            if name.endswith("bias"):
                p.copy_(torch.randn(p.shape, generator=g) * 0.02)
            elif norm_key in name and name.endswith("weight"):
                p.copy_(1.0 + 0.1 * torch.randn(p.shape, generator=g))
            elif p.dim() >= 2:
                fan_in = p[0].numel() if p.shape[0] else 1
                p.copy_(torch.randn(p.shape, generator=g) / math.sqrt(max(fan_in, 1)))
            else:
                p.copy_(torch.randn(p.shape, generator=g) * 0.02)

class Norm(nn.Module):
    """LayerNorm whose affine part is folded into the next Linear at export."""

    def __init__(self, dim, eps=1e-5):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(dim))
        self.bias = nn.Parameter(torch.zeros(dim))
        self.eps = eps
        self.folded = False

    def forward(self, x):
        mu = x.mean(-1, keepdim=True)
        xc = x - mu
        y = xc / torch.sqrt((xc * xc).mean(-1, keepdim=True) + self.eps)
        if self.folded:
            return y
        return y * self.weight + self.bias


def fold_norm(norm, linear):
    """norm(x) @ W^T + b == z @ (W diag(g))^T + (W beta + b), z the plain norm."""
    with torch.no_grad():
        w = linear.weight.clone()
        b = linear.bias.clone() if linear.bias is not None else torch.zeros(w.shape[0])
        linear.weight.copy_(w * norm.weight[None, :])
        if linear.bias is None:
            linear.bias = nn.Parameter(torch.zeros(w.shape[0]))
        linear.bias.copy_(b + w @ norm.bias)
    norm.folded = True


def attention(q, k, v, heads, mask=None):
    """q, k, v: [1, N, E] -> [1, N, E]. Batch 1, as the node runs it."""
    n, e = q.shape[1], q.shape[2]
    hd = e // heads
    q = q.reshape(n, heads, hd).transpose(0, 1)
    k = k.reshape(n, heads, hd).permute(1, 2, 0)
    v = v.reshape(n, heads, hd).transpose(0, 1)
    s = torch.matmul(q, k) * (1.0 / math.sqrt(hd))
    if mask is not None:
        s = s + mask
    a = torch.softmax(s, dim=-1)
    o = torch.matmul(a, v).transpose(0, 1).reshape(1, n, e)
    return o


# ---------------------------------------------------------------- CLIP text


class ClipAttention(nn.Module):
    """nn.MultiheadAttention's parameters (in_proj_*, out_proj), explicit ops."""

    def __init__(self, width, heads):
        super().__init__()
        self.heads = heads
        self.in_proj_weight = nn.Parameter(torch.empty(3 * width, width))
        self.in_proj_bias = nn.Parameter(torch.zeros(3 * width))
        self.out_proj = nn.Linear(width, width)
        self.q = self.k = self.v = None

    def split(self):
        """Three Linears from in_proj, so a Norm can fold into each."""
        w = self.in_proj_weight.shape[1]
        self.q, self.k, self.v = nn.Linear(w, w), nn.Linear(w, w), nn.Linear(w, w)
        with torch.no_grad():
            for i, lin in enumerate((self.q, self.k, self.v)):
                lin.weight.copy_(self.in_proj_weight[i * w:(i + 1) * w])
                lin.bias.copy_(self.in_proj_bias[i * w:(i + 1) * w])

    def forward(self, x, mask):
        if self.q is None:
            w = x.shape[-1]
            q = F.linear(x, self.in_proj_weight[:w], self.in_proj_bias[:w])
            k = F.linear(x, self.in_proj_weight[w:2 * w], self.in_proj_bias[w:2 * w])
            v = F.linear(x, self.in_proj_weight[2 * w:], self.in_proj_bias[2 * w:])
        else:
            q, k, v = self.q(x), self.k(x), self.v(x)
        return self.out_proj(attention(q, k, v, self.heads, mask))


class QuickGELU(nn.Module):
    def forward(self, x):
        return x * torch.sigmoid(1.702 * x)


class ClipBlock(nn.Module):
    def __init__(self, width, heads):
        super().__init__()
        self.attn = ClipAttention(width, heads)
        self.ln_1 = Norm(width)
        self.mlp = nn.Sequential()
        self.mlp.add_module("c_fc", nn.Linear(width, 4 * width))
        self.mlp.add_module("gelu", QuickGELU())
        self.mlp.add_module("c_proj", nn.Linear(4 * width, width))
        self.ln_2 = Norm(width)

    def forward(self, x, mask):
        x = x + self.attn(self.ln_1(x), mask)
        return x + self.mlp(self.ln_2(x))


class ClipTransformer(nn.Module):
    def __init__(self, width, layers, heads):
        super().__init__()
        self.resblocks = nn.ModuleList([ClipBlock(width, heads) for _ in range(layers)])


class ClipText(nn.Module):
    """CLIP's text tower. The exported graph (TextGraph) starts after the
    token embedding: OpenCV 4.6's Gather takes only constant indices, so the
    node looks token ids up in the table itself (the .tokemb file). Output
    [1, 77, P], every position projected; the node reads the row at the
    end-of-text token, so the graph needs no ArgMax either."""

    def __init__(self, vocab=49408, context=77, width=512, layers=12, heads=8, embed_dim=512):
        super().__init__()
        self.context = context
        self.heads = heads
        self.token_embedding = nn.Embedding(vocab, width)
        self.positional_embedding = nn.Parameter(torch.empty(context, width))
        self.transformer = ClipTransformer(width, layers, heads)
        self.ln_final = Norm(width)
        self.text_projection = nn.Parameter(torch.empty(width, embed_dim))
        mask = torch.full((context, context), float("-inf")).triu(1)
        self.register_buffer("mask", mask, persistent=False)
        self.proj = None

    def init_random(self, seed):
        g = torch.Generator().manual_seed(seed)
        init_params(self, g, "ln")

    def prepare_export(self):
        for blk in self.transformer.resblocks:
            blk.attn.split()
            for lin in (blk.attn.q, blk.attn.k, blk.attn.v):
                fold_norm_copy(blk.ln_1, lin)
            blk.ln_1.folded = True
            fold_norm(blk.ln_2, blk.mlp.c_fc)
        width, embed = self.text_projection.shape
        self.proj = nn.Linear(width, embed)
        with torch.no_grad():
            self.proj.weight.copy_(self.text_projection.t())
            self.proj.bias.zero_()
        fold_norm(self.ln_final, self.proj)

    def forward(self, ids):
        return self.forward_embedded(self.token_embedding(ids.long()))

    def forward_embedded(self, x):
        x = x + self.positional_embedding
        for blk in self.transformer.resblocks:
            x = blk(x, self.mask)
        x = self.ln_final(x)
        if self.proj is not None:
            return self.proj(x)
        return x @ self.text_projection

    def embed(self, ids):
        """The reference: CLIP's encode_text, row at argmax(ids)."""
        out = self.forward(ids)
        return out[torch.arange(out.shape[0]), ids.long().argmax(dim=-1)]


class TextGraph(nn.Module):
    """What is exported: [1, 77, width] token embeddings -> [1, 77, P]."""

    def __init__(self, text):
        super().__init__()
        self.text = text

    def forward(self, x):
        return self.text.forward_embedded(x)


def fold_norm_copy(norm, linear):
    """fold_norm without marking the norm, for norms feeding several Linears."""
    folded = norm.folded
    fold_norm(norm, linear)
    norm.folded = folded


# ------------------------------------------------------------ LSeg (DPT ViT)


class VitAttention(nn.Module):
    def __init__(self, dim, heads):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.q = self.k = self.v = None

    def split(self):
        w = self.proj.weight.shape[0]
        self.q, self.k, self.v = nn.Linear(w, w), nn.Linear(w, w), nn.Linear(w, w)
        with torch.no_grad():
            for i, lin in enumerate((self.q, self.k, self.v)):
                lin.weight.copy_(self.qkv.weight[i * w:(i + 1) * w])
                lin.bias.copy_(self.qkv.bias[i * w:(i + 1) * w])

    def forward(self, x):
        if self.q is None:
            w = x.shape[-1]
            qkv = self.qkv(x)
            q, k, v = qkv[..., :w], qkv[..., w:2 * w], qkv[..., 2 * w:]
        else:
            q, k, v = self.q(x), self.k(x), self.v(x)
        return self.proj(attention(q, k, v, self.heads))


class VitMlp(nn.Module):
    def __init__(self, dim, hidden):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x):
        return self.fc2(self.act(self.fc1(x)))


class VitBlock(nn.Module):
    def __init__(self, dim, heads):
        super().__init__()
        self.norm1 = Norm(dim, 1e-6)
        self.attn = VitAttention(dim, heads)
        self.norm2 = Norm(dim, 1e-6)
        self.mlp = VitMlp(dim, 4 * dim)

    def forward(self, x):
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class PatchEmbed(nn.Module):
    def __init__(self, dim, patch):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, patch, patch)


class Vit(nn.Module):
    """timm's VisionTransformer parameter layout (vit_large_patch16_384)."""

    def __init__(self, dim, depth, heads, patch, grid):
        super().__init__()
        self.patch_embed = PatchEmbed(dim, patch)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + grid * grid, dim))
        self.blocks = nn.ModuleList([VitBlock(dim, heads) for _ in range(depth)])


class ProjectReadout(nn.Module):
    """DPT's 'project' readout: Linear(concat(token, cls)) + GELU, for n
    patch tokens. OpenCV 4.6 fails on the token slice + broadcast of cls, so
    both are constant matrix products on the transposed tokens: X^T @ S
    selects the patch tokens, X^T @ R copies cls to every one of them."""

    def __init__(self, dim, n):
        super().__init__()
        self.project = nn.Sequential(nn.Linear(2 * dim, dim), nn.GELU())
        sel = torch.zeros(n + 1, n)
        sel[1:] = torch.eye(n)
        rep = torch.zeros(n + 1, n)
        rep[0] = 1.0
        self.register_buffer("sel", sel, persistent=False)
        self.register_buffer("rep", rep, persistent=False)

    def forward(self, x):
        xt = x.transpose(1, 2)
        y = torch.cat([torch.matmul(xt, self.sel), torch.matmul(xt, self.rep)], dim=1)
        return self.project(y.transpose(1, 2))


class Tokens2Image(nn.Module):
    def __init__(self, dim, h, w):
        super().__init__()
        self.dim, self.h, self.w = dim, h, w

    def forward(self, x):
        return x.transpose(1, 2).reshape(1, self.dim, self.h, self.w)


class ResidualConvUnit(nn.Module):
    def __init__(self, features, bn):
        super().__init__()
        self.bn = bn
        self.conv1 = nn.Conv2d(features, features, 3, padding=1, bias=not bn)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1, bias=not bn)
        if bn:
            self.bn1 = nn.BatchNorm2d(features)
            self.bn2 = nn.BatchNorm2d(features)

    def forward(self, x):
        out = self.conv1(F.relu(x))
        if self.bn:
            out = self.bn1(out)
        out = self.conv2(F.relu(out))
        if self.bn:
            out = self.bn2(out)
        return out + x


class FusionBlock(nn.Module):
    def __init__(self, features, bn):
        super().__init__()
        self.out_conv = nn.Conv2d(features, features, 1)
        self.resConfUnit1 = ResidualConvUnit(features, bn)
        self.resConfUnit2 = ResidualConvUnit(features, bn)

    def forward(self, x, skip=None):
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class Pretrained(nn.Module):
    def __init__(self, vit, post):
        super().__init__()
        self.model = vit
        for i, p in enumerate(post):
            setattr(self, f"act_postprocess{i + 1}", p)


class Scratch(nn.Module):
    def __init__(self, in_feats, features, out_c, bn):
        super().__init__()
        for i, c in enumerate(in_feats):
            setattr(self, f"layer{i + 1}_rn", nn.Conv2d(c, features, 3, padding=1, bias=False))
        for i in range(4):
            setattr(self, f"refinenet{i + 1}", FusionBlock(features, bn))
        self.head1 = nn.Conv2d(features, out_c, 1)


class LSegImage(nn.Module):
    """LSeg's image side: DPT on a ViT (hooks at 4 blocks, 'project'
    readout, reassemble at 1/4..1/32, RefineNet fusion) and the 1x1 head to
    the CLIP dimension. Input [1,3,H,W] normalised RGB, H and W multiples of
    32; output [1, out_c, H/2, W/2], the per-pixel features before LSeg's
    normalisation."""

    def __init__(self, height, width, dim=1024, depth=24, heads=16, hooks=(5, 11, 17, 23),
                 feats=(256, 512, 1024, 1024), features=256, out_c=512, patch=16, bn=True,
                 pos_grid=24):
        super().__init__()
        if height % 32 or width % 32:
            raise ValueError(f"input {width}x{height}: both sides must be multiples of 32")
        self.hooks = hooks
        self.gh, self.gw = height // patch, width // patch
        vit = Vit(dim, depth, heads, patch, pos_grid)
        post = []
        for i, c in enumerate(feats):
            seq = [ProjectReadout(dim, self.gh * self.gw), nn.Identity(), Tokens2Image(dim, self.gh, self.gw),
                   nn.Conv2d(dim, c, 1)]
            if i == 0:
                seq.append(nn.ConvTranspose2d(c, c, 4, 4))
            elif i == 1:
                seq.append(nn.ConvTranspose2d(c, c, 2, 2))
            elif i == 3:
                seq.append(nn.Conv2d(c, c, 3, stride=2, padding=1))
            post.append(nn.Sequential(*seq))
        self.pretrained = Pretrained(vit, post)
        self.scratch = Scratch(feats, features, out_c, bn)
        self.pos = None

    def init_random(self, seed):
        g = torch.Generator().manual_seed(seed)
        init_params(self, g, "norm")
        with torch.no_grad():
            for m in self.modules():
                if isinstance(m, nn.BatchNorm2d):
                    m.weight.copy_(1.0 + 0.1 * torch.randn(m.weight.shape, generator=g))
                    m.running_mean.copy_(0.1 * torch.randn(m.running_mean.shape, generator=g))
                    m.running_var.copy_(1.0 + 0.2 * torch.rand(m.running_var.shape, generator=g))

    def resized_pos(self):
        """DPT's _resize_pos_embed for this input size, computed once."""
        pe = self.pretrained.model.pos_embed
        tok, grid = pe[:, :1], pe[0, 1:]
        old = int(math.sqrt(grid.shape[0]))
        grid = grid.reshape(1, old, old, -1).permute(0, 3, 1, 2)
        grid = F.interpolate(grid, size=(self.gh, self.gw), mode="bilinear", align_corners=False)
        grid = grid.permute(0, 2, 3, 1).reshape(1, self.gh * self.gw, -1)
        return torch.cat([tok, grid], dim=1)

    def prepare_export(self):
        for blk in self.pretrained.model.blocks:
            blk.attn.split()
            for lin in (blk.attn.q, blk.attn.k, blk.attn.v):
                fold_norm_copy(blk.norm1, lin)
            blk.norm1.folded = True
            fold_norm(blk.norm2, blk.mlp.fc1)
        self.pos = nn.Parameter(self.resized_pos().detach())

    def forward(self, x):
        vit = self.pretrained.model
        t = vit.patch_embed.proj(x).flatten(2).transpose(1, 2)
        pos = self.pos if self.pos is not None else self.resized_pos()
        t = torch.cat([vit.cls_token, t], dim=1) + pos
        taps = []
        for i, blk in enumerate(vit.blocks):
            t = blk(t)
            if i in self.hooks:
                taps.append(t)
        layers = []
        for i, tap in enumerate(taps):
            layers.append(getattr(self.pretrained, f"act_postprocess{i + 1}")(tap))
        s = self.scratch
        rn = [getattr(s, f"layer{i + 1}_rn")(layers[i]) for i in range(4)]
        p = s.refinenet4(rn[3])
        p = s.refinenet3(p, rn[2])
        p = s.refinenet2(p, rn[1])
        p = s.refinenet1(p, rn[0])
        return s.head1(p)
