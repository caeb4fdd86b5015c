//! What the reader gives: a tensor's element type, shape, strides and where its bytes are.

/// The element type of a stored tensor, from its storage's class
/// (`torch.FloatStorage` and so on).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TorchDType {
    /// `torch.float64` (`DoubleStorage`).
    F64,
    /// `torch.float32` (`FloatStorage`).
    F32,
    /// `torch.float16` (`HalfStorage`).
    F16,
    /// `torch.bfloat16` (`BFloat16Storage`).
    BF16,
    /// `torch.int64` (`LongStorage`).
    I64,
    /// `torch.int32` (`IntStorage`).
    I32,
    /// `torch.int16` (`ShortStorage`).
    I16,
    /// `torch.int8` (`CharStorage`).
    I8,
    /// `torch.uint8` (`ByteStorage`).
    U8,
    /// `torch.bool` (`BoolStorage`).
    Bool,
}

impl TorchDType {
    pub(super) fn from_storage(name: &str) -> Option<Self> {
        Some(match name {
            "DoubleStorage" => Self::F64,
            "FloatStorage" => Self::F32,
            "HalfStorage" => Self::F16,
            "BFloat16Storage" => Self::BF16,
            "LongStorage" => Self::I64,
            "IntStorage" => Self::I32,
            "ShortStorage" => Self::I16,
            "CharStorage" => Self::I8,
            "ByteStorage" => Self::U8,
            "BoolStorage" => Self::Bool,
            _ => return None,
        })
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            Self::F64 | Self::I64 => 8,
            Self::F32 | Self::I32 => 4,
            Self::F16 | Self::BF16 | Self::I16 => 2,
            Self::I8 | Self::U8 | Self::Bool => 1,
        }
    }

    /// PyTorch's name (`torch.float32`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Self::F64 => "torch.float64",
            Self::F32 => "torch.float32",
            Self::F16 => "torch.float16",
            Self::BF16 => "torch.bfloat16",
            Self::I64 => "torch.int64",
            Self::I32 => "torch.int32",
            Self::I16 => "torch.int16",
            Self::I8 => "torch.int8",
            Self::U8 => "torch.uint8",
            Self::Bool => "torch.bool",
        }
    }
}

/// One tensor of a `state_dict`, as the pickle describes it (its data not read yet).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TorchTensor {
    /// The entry's name (`layer.0.weight`).
    pub name: String,
    /// Element type.
    pub dtype: TorchDType,
    /// Shape.
    pub shape: Vec<usize>,
    /// Strides, in elements.
    pub stride: Vec<usize>,
    /// Offset of the first element in its storage, in elements.
    pub offset: usize,
    /// The storage's key (its member is `data/KEY`).
    pub storage: String,
    /// Elements in the storage.
    pub storage_numel: u64,
}

impl TorchTensor {
    /// Number of elements.
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }
}
