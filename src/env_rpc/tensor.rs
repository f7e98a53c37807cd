//! dm_env_rpc tensors to and from flat f32/f64 values.

use super::wire::dm_env_rpc::v1::tensor::{
    DoubleArray, FloatArray, Int64Array, Payload, StringArray,
};
use super::wire::dm_env_rpc::v1::tensor_spec::value::Payload as BoundPayload;
use super::wire::dm_env_rpc::v1::{Tensor, tensor_spec};

pub(crate) fn floats(values: &[f32]) -> Tensor {
    Tensor {
        payload: Some(Payload::Floats(FloatArray {
            array: values.to_vec(),
        })),
        shape: vec![values.len() as i32],
    }
}

pub(crate) fn doubles(values: &[f64], shape: Vec<i32>) -> Tensor {
    Tensor {
        payload: Some(Payload::Doubles(DoubleArray {
            array: values.to_vec(),
        })),
        shape,
    }
}

pub(crate) fn string(value: &str) -> Tensor {
    Tensor {
        payload: Some(Payload::Strings(StringArray {
            array: vec![value.to_string()],
        })),
        shape: Vec::new(),
    }
}

pub(crate) fn scalar_i64(value: i64) -> Tensor {
    Tensor {
        payload: Some(Payload::Int64s(Int64Array { array: vec![value] })),
        shape: Vec::new(),
    }
}

/// How many elements a spec's shape holds; a variable (negative) dimension is refused, since
/// prac's networks take fixed sizes.
pub(crate) fn element_count(name: &str, shape: &[i32]) -> Result<usize, String> {
    let mut n = 1usize;
    for &d in shape {
        if d < 0 {
            return Err(format!(
                "tensor '{name}' has a variable dimension (shape {shape:?}); prac needs fixed sizes"
            ));
        }
        n *= d as usize;
    }
    Ok(n)
}

/// Writes a numeric tensor's values into `out` as f32 (one value fills every element).
pub(crate) fn read_into(name: &str, tensor: &Tensor, out: &mut [f32]) -> Result<(), String> {
    let values: Vec<f64> = match &tensor.payload {
        Some(Payload::Floats(a)) => a.array.iter().map(|&v| v as f64).collect(),
        Some(Payload::Doubles(a)) => a.array.clone(),
        Some(Payload::Int32s(a)) => a.array.iter().map(|&v| v as f64).collect(),
        Some(Payload::Int64s(a)) => a.array.iter().map(|&v| v as f64).collect(),
        _ => return Err(format!("tensor '{name}' is not numeric")),
    };
    match values.len() {
        1 => out.fill(values[0] as f32),
        n if n == out.len() => {
            for (o, v) in out.iter_mut().zip(values) {
                *o = v as f32;
            }
        }
        n => {
            return Err(format!(
                "tensor '{name}' has {n} values; its spec has {}",
                out.len()
            ));
        }
    }
    if let Some(i) = out.iter().position(|v| !v.is_finite()) {
        return Err(format!(
            "tensor '{name}'[{i}] is {}; every value must be finite",
            out[i]
        ));
    }
    Ok(())
}

pub(crate) fn read_scalar(name: &str, tensor: &Tensor) -> Result<f64, String> {
    let mut value = [0.0f32];
    match &tensor.payload {
        // Kept in f64: returns are sums of many rewards.
        Some(Payload::Doubles(a)) if a.array.len() == 1 && a.array[0].is_finite() => Ok(a.array[0]),
        _ => read_into(name, tensor, &mut value).map(|()| value[0] as f64),
    }
}

pub(crate) fn read_string(tensor: &Tensor) -> Option<String> {
    match &tensor.payload {
        Some(Payload::Strings(a)) => a.array.first().cloned(),
        _ => None,
    }
}

pub(crate) fn read_integer(tensor: &Tensor) -> Option<i64> {
    match &tensor.payload {
        Some(Payload::Int64s(a)) => a.array.first().copied(),
        Some(Payload::Int32s(a)) => a.array.first().map(|&v| v as i64),
        Some(Payload::Uint32s(a)) => a.array.first().map(|&v| v as i64),
        Some(Payload::Uint64s(a)) => a.array.first().map(|&v| v as i64),
        _ => None,
    }
}

/// A spec bound as `n` values (a scalar bound fills them all); None where the spec has none.
pub(crate) fn bound(
    name: &str,
    value: Option<&tensor_spec::Value>,
    n: usize,
) -> Result<Option<Vec<f64>>, String> {
    let Some(payload) = value.and_then(|v| v.payload.as_ref()) else {
        return Ok(None);
    };
    let values: Vec<f64> = match payload {
        BoundPayload::Floats(a) => a.array.iter().map(|&v| v as f64).collect(),
        BoundPayload::Doubles(a) => a.array.clone(),
        BoundPayload::Int8s(a) => a.array.iter().map(|&v| v as i8 as f64).collect(),
        BoundPayload::Int32s(a) => a.array.iter().map(|&v| v as f64).collect(),
        BoundPayload::Int64s(a) => a.array.iter().map(|&v| v as f64).collect(),
        BoundPayload::Uint8s(a) => a.array.iter().map(|&v| v as f64).collect(),
        BoundPayload::Uint32s(a) => a.array.iter().map(|&v| v as f64).collect(),
        BoundPayload::Uint64s(a) => a.array.iter().map(|&v| v as f64).collect(),
    };
    match values.len() {
        1 => Ok(Some(vec![values[0]; n])),
        m if m == n => Ok(Some(values)),
        m => Err(format!(
            "tensor '{name}' has {m} bound values for {n} elements"
        )),
    }
}
