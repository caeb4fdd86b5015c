//! A small builder of ONNX graphs: nodes named in order, constant tensors
//! (initializers), the graph's inputs and outputs, encoded with [`super::proto`].

use super::proto::{self, Attr, Dim, Message};

/// A graph under construction.
#[derive(Debug, Default)]
pub(crate) struct Graph {
    nodes: Vec<Message>,
    initializers: Vec<Message>,
    inputs: Vec<Message>,
    outputs: Vec<Message>,
    count: usize,
    /// Number of nodes added (for the manifest).
    pub node_count: usize,
    /// Number of constant values stored (for the manifest).
    pub constant_values: usize,
}

impl Graph {
    /// An empty graph.
    pub fn new() -> Self {
        Self::default()
    }

    fn fresh(&mut self, hint: &str) -> String {
        self.count += 1;
        format!("{hint}_{}", self.count)
    }

    /// Declares a graph input.
    pub fn input(&mut self, name: &str, elem_type: i32, dims: &[Dim], doc: &str) -> String {
        self.inputs
            .push(proto::value_info(name, elem_type, dims, doc));
        name.to_string()
    }

    /// Declares `value` (a node's output) as the graph output `name` through an
    /// `Identity` node, so that outputs carry their public names.
    pub fn output(&mut self, value: &str, name: &str, elem_type: i32, dims: &[Dim], doc: &str) {
        self.push("Identity", &[value], name, &[]);
        self.outputs
            .push(proto::value_info(name, elem_type, dims, doc));
    }

    /// A float constant (an initializer) named after `hint`.
    pub(crate) fn constant_f32(&mut self, hint: &str, dims: &[usize], values: &[f32]) -> String {
        debug_assert_eq!(dims.iter().product::<usize>(), values.len());
        let name = self.fresh(hint);
        self.constant_values += values.len();
        self.initializers
            .push(proto::tensor_f32(&name, dims, values));
        name
    }

    /// An int64 constant (an initializer) named after `hint`.
    pub(crate) fn constant_i64(&mut self, hint: &str, dims: &[usize], values: &[i64]) -> String {
        debug_assert_eq!(dims.iter().product::<usize>(), values.len());
        let name = self.fresh(hint);
        self.constant_values += values.len();
        self.initializers
            .push(proto::tensor_i64(&name, dims, values));
        name
    }

    /// A node of `op` on `inputs` with one output (a fresh name), which it returns.
    pub fn op(&mut self, op: &str, inputs: &[&str], attrs: &[(&str, Attr)]) -> String {
        let out = self.fresh(&op.to_ascii_lowercase());
        self.push(op, inputs, &out, attrs);
        out
    }

    fn push(&mut self, op: &str, inputs: &[&str], out: &str, attrs: &[(&str, Attr)]) {
        let name = format!("{op}_{}", self.node_count);
        let inputs: Vec<String> = inputs.iter().map(|s| s.to_string()).collect();
        let attrs: Vec<(String, Attr)> = attrs
            .iter()
            .map(|(k, v)| (k.to_string(), v.clone()))
            .collect();
        self.nodes
            .push(proto::node(op, &name, &inputs, &[out.to_string()], &attrs));
        self.node_count += 1;
    }

    /// The graph as a `GraphProto`.
    pub fn finish(self, name: &str, doc: &str) -> Message {
        proto::graph(
            name,
            doc,
            &self.nodes,
            &self.initializers,
            &self.inputs,
            &self.outputs,
        )
    }
}
