//! The architecture check: the module graph of the three crates, read with
//! `syn` from the sources (not from the compiler), held to three rules.
//!
//! 1. **No cycles between siblings.** Every path in non-test code that names
//!    an item of another module of the same crate (in a `use`, an expression,
//!    a type, a pattern, or a macro's arguments) is an arrow from the module
//!    it is written in to the module that defines the item. An arrow from A to
//!    B is counted between the two children of their lowest common ancestor
//!    that contain A and B. A module's own items (those written in its
//!    `mod.rs`/`lib.rs`, not in a child) form one more node beside its
//!    children, named after the module. So an ancestor reaching into a
//!    descendant is an arrow from its own items down to that child's branch,
//!    and a descendant using an item of its ancestor's own is an arrow from
//!    its branch up to the ancestor's own items. Each alone is allowed; both
//!    together are a cycle (`farm/mod.rs` using `local`, and `local` using
//!    `farm::Shared`). Among the nodes of one parent, the arrows must not
//!    close a cycle.
//! 2. **Arrows go down the layers.** Each crate declares its rooms (the
//!    crate root's children, and `crate` for the root's own items) from the
//!    bottom up in [`LAYERS`]; every arrow between two rooms must run from a
//!    higher level to a lower one.
//! 3. **Short functions.** No function outside tests runs over
//!    [`MAX_FN_LINES`] lines, counted from the line of `fn` to the line of
//!    its closing brace.
//!
//! The unit is the file: an inline module (`mod x86 { … }`) belongs to the
//! file it is written in, so its arrows are that file's.
//!
//! What the check cannot see: a method call (`x.support()`) names no path,
//! so the module that defines the method is known only to the type checker;
//! the check counts the paths (types, functions, constants, variants, traits)
//! a module writes.
//!
//! Re-exports are seen through: a path that reaches an item through a `use`
//! (public or private) is followed to the module that defines it, so a
//! re-export never hides an arrow. A `use` line counts as an arrow itself
//! when it is private (an import for the module's own code); a `pub` one is
//! only a signpost and counts at the places that use it. Items under
//! `#[cfg(test)]` and functions marked `#[test]` are skipped; doc comments
//! hold no paths.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use proc_macro2::{TokenStream, TokenTree};
use syn::spanned::Spanned;
use syn::visit::Visit;

/// The rooms of each crate, bottom level first: the crate root's children,
/// and `crate` for the items written in `lib.rs` itself. Rooms on one level
/// must not use each other.
const LAYERS: &[(&str, &[&[&str]])] = &[
    (
        "hypertexture",
        &[
            &["math"],
            &["mesh"],
            &["desc"],
            &["field"],
            &["pse"],
            &["scene"],
            &["render"],
        ],
    ),
    (
        "coordinator",
        &[
            &["files", "guard", "logging"],
            &["image"],
            &["farm"],
            &["pipeline"],
            &["service"],
            &["cli"],
            &["crate"],
        ],
    ),
    (
        "worker",
        &[
            &["body", "cache", "cpu", "idle", "logging", "signal"],
            &["crate"],
            &["connection"],
            &["assets", "tiles", "withdrawals"],
            &["render"],
            &["register"],
            &["session"],
            &["run"],
            &["cli"],
        ],
    ),
];

/// The longest a function outside tests may be, in lines.
const MAX_FN_LINES: usize = 100;

/// The crates checked: name, root file (relative to the workspace).
const CRATES: &[(&str, &str)] = &[
    ("hypertexture", "shared/src/lib.rs"),
    ("coordinator", "coordinator/src/lib.rs"),
    ("coordinator-main", "coordinator/src/main.rs"),
    ("worker", "worker/src/lib.rs"),
    ("worker-main", "worker/src/main.rs"),
];

// ---------------------------------------------------------------------------
// The module tree
// ---------------------------------------------------------------------------

/// One module of a crate.
#[derive(Debug, Default)]
struct Module {
    /// Its path from the crate root (empty for the root).
    path: Vec<String>,
    /// The module of the file it is written in: itself, or for an inline
    /// `mod name { … }` the module of the enclosing file.
    file_module: usize,
    parent: Option<usize>,
    children: BTreeMap<String, usize>,
    /// Names brought in by `use`: name → the path as written.
    aliases: BTreeMap<String, Vec<String>>,
    /// Paths written in the module's non-test code, with where.
    paths: Vec<Written>,
}

/// A path as written somewhere in a module.
#[derive(Debug, Clone)]
struct Written {
    segments: Vec<String>,
    file: String,
    line: usize,
    /// Whether a lone first segment may name a module (true in `use` trees;
    /// in an expression a single name is a value, never a module).
    from_use: bool,
}

/// A function body's extent.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct LongFn {
    lines: usize,
    file: String,
    line: usize,
    name: String,
}

#[derive(Debug)]
struct Crate {
    name: String,
    modules: Vec<Module>,
    long_fns: Vec<LongFn>,
}

/// Reads a file of the crate; `None` if it does not exist.
type Reader<'a> = &'a dyn Fn(&Path) -> Option<String>;

impl Crate {
    /// Parses the crate whose root file is `root`, following `mod` items.
    fn load(name: &str, root: &Path, read: Reader) -> Result<Crate, String> {
        let mut krate = Crate {
            name: name.to_string(),
            modules: vec![Module::default()],
            long_fns: Vec::new(),
        };
        let dir = root.parent().unwrap_or(Path::new("")).to_path_buf();
        krate.load_file(0, root, dir, read)?;
        Ok(krate)
    }

    fn load_file(
        &mut self,
        module: usize,
        file: &Path,
        dir: PathBuf,
        read: Reader,
    ) -> Result<(), String> {
        let text = read(file).ok_or_else(|| format!("{}: cannot read", file.display()))?;
        let ast = syn::parse_file(&text).map_err(|error| {
            let at = error.span().start();
            format!("{}:{}:{}: {error}", file.display(), at.line, at.column + 1)
        })?;
        self.load_items(module, &ast.items, file, dir, read)
    }

    fn load_items(
        &mut self,
        module: usize,
        items: &[syn::Item],
        file: &Path,
        dir: PathBuf,
        read: Reader,
    ) -> Result<(), String> {
        let shown = file.display().to_string();
        for item in items {
            if is_test_only(item_attrs(item)) {
                continue;
            }
            match item {
                syn::Item::Mod(declared) => {
                    let name = declared.ident.to_string();
                    let child = self.add_child(module, &name);
                    match &declared.content {
                        Some((_, inner)) => {
                            self.modules[child].file_module = self.modules[module].file_module;
                            self.load_items(child, inner, file, dir.join(&name), read)?;
                        }
                        None => {
                            let flat = dir.join(format!("{name}.rs"));
                            let nested = dir.join(&name).join("mod.rs");
                            if read(&flat).is_some() {
                                self.load_file(child, &flat, dir.join(&name), read)?;
                            } else if read(&nested).is_some() {
                                self.load_file(child, &nested, dir.join(&name), read)?;
                            } else {
                                return Err(format!(
                                    "{shown}:{}: no file for `mod {name}`",
                                    declared.span().start().line
                                ));
                            }
                        }
                    }
                }
                _ => {
                    let mut collector = Collector {
                        file: &shown,
                        paths: Vec::new(),
                        aliases: Vec::new(),
                        long_fns: Vec::new(),
                    };
                    collector.visit_item(item);
                    let Collector {
                        paths,
                        aliases,
                        long_fns,
                        ..
                    } = collector;
                    self.modules[module].paths.extend(paths);
                    self.modules[module].aliases.extend(aliases);
                    self.long_fns.extend(long_fns);
                }
            }
        }
        Ok(())
    }

    fn add_child(&mut self, parent: usize, name: &str) -> usize {
        let mut path = self.modules[parent].path.clone();
        path.push(name.to_string());
        let index = self.modules.len();
        self.modules.push(Module {
            path,
            file_module: index,
            parent: Some(parent),
            ..Module::default()
        });
        self.modules[parent]
            .children
            .insert(name.to_string(), index);
        index
    }

    /// The module that defines what `segments`, written in module `from`,
    /// names; `None` for anything outside the crate (std, other crates,
    /// local variables, generic parameters).
    fn resolve(
        &self,
        from: usize,
        segments: &[String],
        may_be_module: bool,
        depth: u32,
    ) -> Option<usize> {
        if depth > 16 || segments.is_empty() {
            return None;
        }
        let first = segments[0].as_str();
        let (start, rest) = match first {
            "crate" => (0, &segments[1..]),
            "self" => (from, &segments[1..]),
            "super" => {
                let mut at = from;
                let mut taken = 0;
                while segments.get(taken).map(String::as_str) == Some("super") {
                    at = self.modules[at].parent?;
                    taken += 1;
                }
                (at, &segments[taken..])
            }
            _ => {
                if let Some(&child) = self.modules[from].children.get(first)
                    && (segments.len() > 1 || may_be_module)
                {
                    (child, &segments[1..])
                } else if let Some(alias) = self.modules[from].aliases.get(first) {
                    let mut full = alias.clone();
                    full.extend_from_slice(&segments[1..]);
                    return self.resolve_alias(
                        from,
                        &full,
                        segments.len() > 1 || may_be_module,
                        depth,
                    );
                } else {
                    return None;
                }
            }
        };
        self.walk(start, rest, depth)
    }

    /// Follows an alias written in module `at`: a `use` path's first segment
    /// is read from the module that holds the `use` (`crate`, `self`,
    /// `super`, a child, another alias; anything else is another crate).
    fn resolve_alias(
        &self,
        at: usize,
        full: &[String],
        may_be_module: bool,
        depth: u32,
    ) -> Option<usize> {
        self.resolve(at, full, may_be_module, depth + 1)
    }

    fn walk(&self, mut at: usize, rest: &[String], depth: u32) -> Option<usize> {
        for (i, segment) in rest.iter().enumerate() {
            if let Some(&child) = self.modules[at].children.get(segment) {
                at = child;
                continue;
            }
            if let Some(alias) = self.modules[at].aliases.get(segment) {
                let mut full = alias.clone();
                full.extend_from_slice(&rest[i + 1..]);
                return self.resolve_alias(at, &full, true, depth);
            }
            // An item defined in `at` (or one the sources do not show, such
            // as a macro-made item): `at` defines it.
            return Some(at);
        }
        Some(at)
    }

    /// Every arrow between two different modules.
    fn arrows(&self) -> Vec<Arrow> {
        let mut arrows = Vec::new();
        for (index, module) in self.modules.iter().enumerate() {
            for written in &module.paths {
                let Some(target) = self.resolve(index, &written.segments, written.from_use, 0)
                else {
                    continue;
                };
                let (source, target) = (module.file_module, self.modules[target].file_module);
                if target == source {
                    continue;
                }
                let from = &self.modules[source].path;
                let to = &self.modules[target].path;
                let common = from.iter().zip(to).take_while(|(a, b)| a == b).count();
                let parent = from[..common].to_vec();
                let node = |path: &[String]| -> String {
                    path.get(common)
                        .cloned()
                        .unwrap_or_else(|| own_items(&parent))
                };
                arrows.push(Arrow {
                    parent: parent.clone(),
                    from: node(from),
                    to: node(to),
                    file: written.file.clone(),
                    line: written.line,
                    text: written.segments.join("::"),
                });
            }
        }
        arrows.sort();
        arrows.dedup();
        arrows
    }
}

/// The node that stands for a module's own items among its children.
fn own_items(parent: &[String]) -> String {
    match parent.last() {
        Some(name) => format!("{name} (own items)"),
        None => "crate".to_string(),
    }
}

/// An arrow between two nodes under one parent, with where it is written.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct Arrow {
    parent: Vec<String>,
    from: String,
    to: String,
    file: String,
    line: usize,
    text: String,
}

// ---------------------------------------------------------------------------
// Collecting paths and function lengths from one item
// ---------------------------------------------------------------------------

struct Collector<'a> {
    file: &'a str,
    paths: Vec<Written>,
    aliases: Vec<(String, Vec<String>)>,
    long_fns: Vec<LongFn>,
}

impl Collector<'_> {
    fn push(&mut self, segments: Vec<String>, line: usize, from_use: bool) {
        if !segments.is_empty() {
            self.paths.push(Written {
                segments,
                file: self.file.to_string(),
                line,
                from_use,
            });
        }
    }

    fn use_tree(&mut self, prefix: &mut Vec<String>, tree: &syn::UseTree, counts: bool) {
        match tree {
            syn::UseTree::Path(path) => {
                prefix.push(path.ident.to_string());
                self.use_tree(prefix, &path.tree, counts);
                prefix.pop();
            }
            syn::UseTree::Name(name) => {
                let line = name.ident.span().start().line;
                let ident = name.ident.to_string();
                let mut full = prefix.clone();
                let alias = if ident == "self" {
                    prefix.last().cloned()
                } else {
                    full.push(ident.clone());
                    Some(ident)
                };
                if let Some(alias) = alias {
                    self.aliases.push((alias, full.clone()));
                }
                if counts {
                    self.push(full, line, true);
                }
            }
            syn::UseTree::Rename(rename) => {
                let line = rename.ident.span().start().line;
                let mut full = prefix.clone();
                if rename.ident != "self" {
                    full.push(rename.ident.to_string());
                }
                if rename.rename != "_" {
                    self.aliases.push((rename.rename.to_string(), full.clone()));
                }
                if counts {
                    self.push(full, line, true);
                }
            }
            syn::UseTree::Glob(glob) => {
                if counts {
                    self.push(prefix.clone(), glob.star_token.span.start().line, true);
                }
            }
            syn::UseTree::Group(group) => {
                for tree in &group.items {
                    self.use_tree(prefix, tree, counts);
                }
            }
        }
    }

    fn function(&mut self, name: &syn::Ident, fn_token: &syn::token::Fn, block: &syn::Block) {
        let start = fn_token.span.start().line;
        let end = block.brace_token.span.close().end().line;
        let lines = end + 1 - start;
        if lines > MAX_FN_LINES {
            self.long_fns.push(LongFn {
                lines,
                file: self.file.to_string(),
                line: start,
                name: name.to_string(),
            });
        }
    }

    /// Paths inside a macro's arguments: every `a::b…` run of two or more
    /// segments (a lone name in a macro may be a local variable).
    fn tokens(&mut self, tokens: TokenStream) {
        let mut run: Vec<String> = Vec::new();
        let mut line = 0;
        let mut colons = 0;
        let flush = |this: &mut Self, run: &mut Vec<String>, line: usize| {
            if run.len() > 1 {
                this.push(std::mem::take(run), line, false);
            }
            run.clear();
        };
        for token in tokens {
            match token {
                TokenTree::Ident(ident) => {
                    if run.is_empty() || colons != 2 {
                        flush(self, &mut run, line);
                        line = ident.span().start().line;
                    }
                    run.push(ident.to_string());
                    colons = 0;
                }
                TokenTree::Punct(punct)
                    if punct.as_char() == ':' && !run.is_empty() && colons < 2 =>
                {
                    colons += 1;
                }
                TokenTree::Group(group) => {
                    flush(self, &mut run, line);
                    colons = 0;
                    self.tokens(group.stream());
                }
                _ => {
                    flush(self, &mut run, line);
                    colons = 0;
                }
            }
        }
        flush(self, &mut run, line);
    }
}

impl<'ast> Visit<'ast> for Collector<'_> {
    fn visit_item(&mut self, item: &'ast syn::Item) {
        if is_test_only(item_attrs(item)) {
            return;
        }
        syn::visit::visit_item(self, item);
    }

    fn visit_item_use(&mut self, item: &'ast syn::ItemUse) {
        let private = matches!(item.vis, syn::Visibility::Inherited);
        let mut prefix = Vec::new();
        if item.leading_colon.is_none() {
            self.use_tree(&mut prefix, &item.tree, private);
        }
    }

    fn visit_item_mod(&mut self, _: &'ast syn::ItemMod) {
        // A module inside a function body: rare, and not a room of its own.
    }

    fn visit_item_fn(&mut self, item: &'ast syn::ItemFn) {
        if is_test_only(&item.attrs) {
            return;
        }
        self.function(&item.sig.ident, &item.sig.fn_token, &item.block);
        syn::visit::visit_item_fn(self, item);
    }

    fn visit_impl_item(&mut self, item: &'ast syn::ImplItem) {
        let attrs: &[syn::Attribute] = match item {
            syn::ImplItem::Const(item) => &item.attrs,
            syn::ImplItem::Fn(item) => &item.attrs,
            syn::ImplItem::Type(item) => &item.attrs,
            syn::ImplItem::Macro(item) => &item.attrs,
            _ => &[],
        };
        if is_test_only(attrs) {
            return;
        }
        syn::visit::visit_impl_item(self, item);
    }

    fn visit_impl_item_fn(&mut self, item: &'ast syn::ImplItemFn) {
        self.function(&item.sig.ident, &item.sig.fn_token, &item.block);
        syn::visit::visit_impl_item_fn(self, item);
    }

    fn visit_trait_item_fn(&mut self, item: &'ast syn::TraitItemFn) {
        if let Some(block) = &item.default {
            self.function(&item.sig.ident, &item.sig.fn_token, block);
        }
        syn::visit::visit_trait_item_fn(self, item);
    }

    fn visit_path(&mut self, path: &'ast syn::Path) {
        if path.leading_colon.is_none() {
            let segments: Vec<String> = path.segments.iter().map(|s| s.ident.to_string()).collect();
            self.push(segments, path.span().start().line, false);
        }
        syn::visit::visit_path(self, path);
    }

    fn visit_visibility(&mut self, _: &'ast syn::Visibility) {
        // `pub(crate)`, `pub(super)`, `pub(in path)` say who may see an
        // item; they use nothing.
    }

    fn visit_attribute(&mut self, _: &'ast syn::Attribute) {
        // Attributes name tools and derives, and doc comments are text.
    }

    fn visit_macro(&mut self, mac: &'ast syn::Macro) {
        self.visit_path(&mac.path);
        self.tokens(mac.tokens.clone());
    }
}

fn item_attrs(item: &syn::Item) -> &[syn::Attribute] {
    match item {
        syn::Item::Const(item) => &item.attrs,
        syn::Item::Enum(item) => &item.attrs,
        syn::Item::ExternCrate(item) => &item.attrs,
        syn::Item::Fn(item) => &item.attrs,
        syn::Item::ForeignMod(item) => &item.attrs,
        syn::Item::Impl(item) => &item.attrs,
        syn::Item::Macro(item) => &item.attrs,
        syn::Item::Mod(item) => &item.attrs,
        syn::Item::Static(item) => &item.attrs,
        syn::Item::Struct(item) => &item.attrs,
        syn::Item::Trait(item) => &item.attrs,
        syn::Item::TraitAlias(item) => &item.attrs,
        syn::Item::Type(item) => &item.attrs,
        syn::Item::Union(item) => &item.attrs,
        syn::Item::Use(item) => &item.attrs,
        _ => &[],
    }
}

/// `#[test]`, `#[cfg(test)]` or a `cfg` that needs `test` (`all(test, …)`).
fn is_test_only(attrs: &[syn::Attribute]) -> bool {
    attrs.iter().any(|attr| {
        if attr.path().is_ident("test") {
            return true;
        }
        if !attr.path().is_ident("cfg") {
            return false;
        }
        let Ok(list) = attr.meta.require_list() else {
            return false;
        };
        let text: String = list.tokens.to_string().split_whitespace().collect();
        text == "test"
            || (text.starts_with("all(") && text.split([',', '(', ')']).any(|word| word == "test"))
    })
}

// ---------------------------------------------------------------------------
// The three rules
// ---------------------------------------------------------------------------

/// The cycles among the children of each parent, each with its arrows.
fn cycles(krate: &Crate) -> Vec<String> {
    let arrows = krate.arrows();
    let mut by_parent: BTreeMap<Vec<String>, Vec<&Arrow>> = BTreeMap::new();
    for arrow in &arrows {
        by_parent
            .entry(arrow.parent.clone())
            .or_default()
            .push(arrow);
    }
    let mut found = Vec::new();
    for (parent, arrows) in by_parent {
        let mut next: BTreeMap<&str, BTreeSet<&str>> = BTreeMap::new();
        for arrow in &arrows {
            next.entry(&arrow.from).or_default().insert(&arrow.to);
            next.entry(&arrow.to).or_default();
        }
        for component in strongly_connected(&next) {
            if component.len() < 2 {
                continue;
            }
            let place = if parent.is_empty() {
                format!("{} (crate root)", krate.name)
            } else {
                format!("{}::{}", krate.name, parent.join("::"))
            };
            let mut text = format!(
                "cycle among the children of {place}: {}\n",
                component.iter().cloned().collect::<Vec<_>>().join(", ")
            );
            for arrow in arrows.iter().filter(|a| {
                component.contains(a.from.as_str()) && component.contains(a.to.as_str())
            }) {
                let _ = writeln!(
                    text,
                    "    {}:{}: {} -> {} ({})",
                    arrow.file, arrow.line, arrow.from, arrow.to, arrow.text
                );
            }
            found.push(text);
        }
    }
    found
}

/// Tarjan's strongly connected components, each as a set of node names.
fn strongly_connected<'a>(next: &BTreeMap<&'a str, BTreeSet<&'a str>>) -> Vec<BTreeSet<&'a str>> {
    struct State<'a> {
        index: BTreeMap<&'a str, usize>,
        low: BTreeMap<&'a str, usize>,
        stack: Vec<&'a str>,
        on_stack: BTreeSet<&'a str>,
        out: Vec<BTreeSet<&'a str>>,
    }
    fn visit<'a>(
        node: &'a str,
        next: &BTreeMap<&'a str, BTreeSet<&'a str>>,
        state: &mut State<'a>,
    ) {
        let n = state.index.len();
        state.index.insert(node, n);
        state.low.insert(node, n);
        state.stack.push(node);
        state.on_stack.insert(node);
        for &to in &next[node] {
            if !state.index.contains_key(to) {
                visit(to, next, state);
                let low = state.low[node].min(state.low[to]);
                state.low.insert(node, low);
            } else if state.on_stack.contains(to) {
                let low = state.low[node].min(state.index[to]);
                state.low.insert(node, low);
            }
        }
        if state.low[node] == state.index[node] {
            let mut component = BTreeSet::new();
            while let Some(top) = state.stack.pop() {
                state.on_stack.remove(top);
                component.insert(top);
                if top == node {
                    break;
                }
            }
            state.out.push(component);
        }
    }
    let mut state = State {
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        out: Vec::new(),
    };
    for &node in next.keys() {
        if !state.index.contains_key(node) {
            visit(node, next, &mut state);
        }
    }
    state.out
}

/// Arrows between rooms of the crate root that run up (or sideways across a
/// level), and rooms missing from the table.
fn layer_breaches(krate: &Crate, levels: &[&[&str]]) -> Vec<String> {
    let level = |room: &str| levels.iter().position(|rooms| rooms.contains(&room));
    let mut found = Vec::new();
    for arrow in krate.arrows().iter().filter(|a| a.parent.is_empty()) {
        match (level(&arrow.from), level(&arrow.to)) {
            (Some(from), Some(to)) if from > to => {}
            (Some(_), Some(_)) => found.push(format!(
                "{}:{}: {} -> {} does not run down the layers of {} ({})",
                arrow.file, arrow.line, arrow.from, arrow.to, krate.name, arrow.text
            )),
            (from, to) => {
                let missing = if from.is_none() {
                    &arrow.from
                } else {
                    &arrow.to
                };
                let _ = to;
                found.push(format!(
                    "{}:{}: room `{missing}` of {} is not in the layer table ({} -> {})",
                    arrow.file, arrow.line, krate.name, arrow.from, arrow.to
                ));
            }
        }
    }
    found
}

fn long_functions(krate: &Crate) -> Vec<String> {
    let mut long = krate.long_fns.clone();
    long.sort_by(|a, b| b.lines.cmp(&a.lines).then(a.cmp(b)));
    long.iter()
        .map(|f| format!("{}:{}: fn {} is {} lines", f.file, f.line, f.name, f.lines))
        .collect()
}

// ---------------------------------------------------------------------------
// The workspace
// ---------------------------------------------------------------------------

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the coordinator sits in the workspace")
        .to_path_buf()
}

/// Every crate of the workspace, parsed; file names relative to the workspace.
fn crates() -> Vec<Crate> {
    let root = workspace();
    let read = |path: &Path| std::fs::read_to_string(root.join(path)).ok();
    CRATES
        .iter()
        .map(|(name, file)| {
            Crate::load(name, Path::new(file), &read).unwrap_or_else(|error| panic!("{error}"))
        })
        .collect()
}

fn levels_of(name: &str) -> Option<&'static [&'static [&'static str]]> {
    LAYERS
        .iter()
        .find(|(crate_name, _)| *crate_name == name)
        .map(|(_, levels)| *levels)
}

/// Debts the check knows of, each as the first line of its report says it:
/// a breach listed here does not fail the check, and a listed one that is
/// no longer found fails it until it is struck off, so the list only
/// shrinks.
const KNOWN: &[&str] = &[];

fn verdict(rule: &str, found: Vec<String>) {
    let first = |f: &String| f.lines().next().unwrap_or_default().to_string();
    let new: Vec<String> = found
        .into_iter()
        .filter(|f| !KNOWN.iter().any(|k| first(f).contains(k)))
        .collect();
    assert!(
        new.is_empty(),
        "{rule}: {} found\n{}",
        new.len(),
        new.join("\n")
    );
}

#[test]
fn no_cycles_between_sibling_modules() {
    verdict("import cycles", crates().iter().flat_map(cycles).collect());
}

#[test]
fn arrows_run_down_the_layers() {
    let mut found = Vec::new();
    for krate in crates() {
        if let Some(levels) = levels_of(&krate.name) {
            found.extend(layer_breaches(&krate, levels));
        }
    }
    verdict("arrows up a layer", found);
}

#[test]
fn no_function_over_the_limit() {
    verdict(
        &format!("functions over {MAX_FN_LINES} lines"),
        crates().iter().flat_map(long_functions).collect(),
    );
}

/// Every debt in [`KNOWN`] is still owed: one that was paid is struck off.
#[test]
fn every_known_debt_is_still_owed() {
    let krates = crates();
    let mut found: Vec<String> = krates.iter().flat_map(cycles).collect();
    found.extend(krates.iter().flat_map(long_functions));
    for krate in &krates {
        if let Some(levels) = levels_of(&krate.name) {
            found.extend(layer_breaches(krate, levels));
        }
    }
    let paid: Vec<&str> = KNOWN
        .iter()
        .copied()
        .filter(|k| {
            !found
                .iter()
                .any(|f| f.lines().next().unwrap_or_default().contains(k))
        })
        .collect();
    assert!(paid.is_empty(), "paid, strike these off KNOWN: {paid:?}");
}

// ---------------------------------------------------------------------------
// The rules on small synthetic crates
// ---------------------------------------------------------------------------

/// A crate made of `(path, text)` files, rooted at `lib.rs`.
fn synthetic(files: &[(&str, &str)]) -> Crate {
    let map: BTreeMap<PathBuf, String> = files
        .iter()
        .map(|(path, text)| (PathBuf::from(path), text.to_string()))
        .collect();
    let read = |path: &Path| map.get(path).cloned();
    Crate::load("synthetic", Path::new("lib.rs"), &read).unwrap_or_else(|error| panic!("{error}"))
}

#[test]
fn a_chain_of_three_siblings_is_a_cycle() {
    // bake → service → cli → bake, each through a different kind of path.
    let krate = synthetic(&[
        (
            "lib.rs",
            "pub mod cli;\npub mod pipeline;\npub mod service;\n",
        ),
        ("pipeline/mod.rs", "pub mod bake;\n"),
        (
            "pipeline/bake.rs",
            "pub struct BakeConfig;\npub fn run() { crate::service::expand_pattern(); }\n",
        ),
        (
            "service/mod.rs",
            "use crate::cli::ServeArgs;\npub fn expand_pattern() {}\npub fn serve(_: ServeArgs) {}\n",
        ),
        (
            "cli.rs",
            "pub struct ServeArgs;\npub struct Args { pub bake: crate::pipeline::bake::BakeConfig }\n",
        ),
    ]);
    let found = cycles(&krate);
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(found[0].contains("cli, pipeline, service"), "{}", found[0]);
    assert!(
        found[0].contains("pipeline/bake.rs:2: pipeline -> service"),
        "{}",
        found[0]
    );
    assert!(
        found[0].contains("service/mod.rs:1: service -> cli"),
        "{}",
        found[0]
    );
    assert!(
        found[0].contains("cli.rs:2: cli -> pipeline"),
        "{}",
        found[0]
    );
}

#[test]
fn a_parent_and_a_child_using_each_other_is_a_cycle() {
    // farm/mod.rs uses `local`, and `local` uses the farm's own `Shared`.
    let krate = synthetic(&[
        ("lib.rs", "pub mod farm;\n"),
        (
            "farm/mod.rs",
            "mod local;\npub struct Shared;\npub fn start() { local::spawn(); }\n",
        ),
        (
            "farm/local.rs",
            "use super::Shared;\npub fn spawn() { let _ = Shared; }\n",
        ),
    ]);
    let found = cycles(&krate);
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(
        found[0].contains("children of synthetic::farm"),
        "{}",
        found[0]
    );
    assert!(
        found[0].contains("farm/local.rs:1: local -> farm (own items)"),
        "{}",
        found[0]
    );
    assert!(
        found[0].contains("farm/mod.rs:3: farm (own items) -> local"),
        "{}",
        found[0]
    );
}

#[test]
fn an_ancestor_using_a_descendant_alone_is_allowed() {
    let krate = synthetic(&[
        ("lib.rs", "pub mod farm;\n"),
        (
            "farm/mod.rs",
            "mod local;\npub use local::Spawned;\npub fn start() { local::spawn(); }\n",
        ),
        ("farm/local.rs", "pub struct Spawned;\npub fn spawn() {}\n"),
    ]);
    assert_eq!(cycles(&krate), Vec::<String>::new());
}

#[test]
fn siblings_deep_in_the_tree_are_checked() {
    // field/density/dmf ↔ field/density/lanes, the first through an alias.
    let krate = synthetic(&[
        ("lib.rs", "pub mod field;\n"),
        ("field/mod.rs", "pub mod density;\n"),
        ("field/density/mod.rs", "pub mod dmf;\npub mod lanes;\n"),
        (
            "field/density/dmf/mod.rs",
            "use super::lanes;\npub struct Dmf;\npub fn eval() { lanes::run8(); }\n",
        ),
        (
            "field/density/lanes.rs",
            "pub fn run8() { let _ = super::dmf::Dmf; }\n",
        ),
    ]);
    let found = cycles(&krate);
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(
        found[0].contains("children of synthetic::field::density: dmf, lanes"),
        "{}",
        found[0]
    );
    assert!(
        found[0].contains("field/density/dmf/mod.rs:3: dmf -> lanes"),
        "{}",
        found[0]
    );
    assert!(
        found[0].contains("field/density/lanes.rs:1: lanes -> dmf"),
        "{}",
        found[0]
    );
}

#[test]
fn a_re_export_does_not_hide_an_arrow() {
    // density ↔ distortion and density ↔ motion, distortion reaching the
    // density through field's re-export, motion inside a macro's arguments.
    let krate = synthetic(&[
        ("lib.rs", "pub mod field;\n"),
        (
            "field/mod.rs",
            "pub mod density;\npub mod distortion;\npub mod motion;\npub use density::Density;\n",
        ),
        (
            "field/density.rs",
            "use super::distortion::Warp;\npub struct Density(pub Warp, pub super::motion::Path);\n",
        ),
        (
            "field/distortion.rs",
            "pub struct Warp;\npub fn of(d: &crate::field::Density) {}\n",
        ),
        (
            "field/motion.rs",
            "pub struct Path;\npub fn at() { assert!(crate::field::density::Density::ok()); }\n",
        ),
    ]);
    let found = cycles(&krate);
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(
        found[0].contains("density, distortion, motion"),
        "{}",
        found[0]
    );
    assert!(
        found[0].contains("field/distortion.rs:2: distortion -> density (crate::field::Density)"),
        "{}",
        found[0]
    );
    assert!(
        found[0].contains("field/motion.rs:2: motion -> density"),
        "{}",
        found[0]
    );
    // The re-export line in field/mod.rs is not an arrow of field's own.
    assert!(!found[0].contains("field/mod.rs"), "{}", found[0]);
}

#[test]
fn test_code_and_other_crates_are_not_arrows() {
    let krate = synthetic(&[
        ("lib.rs", "pub mod a;\npub mod b;\n"),
        (
            "a.rs",
            "pub(crate) struct A;\npub(super) fn g() {}\n#[cfg(test)]\nmod tests { use crate::b::B; }\n#[test]\nfn t() { crate::b::f(); }\n",
        ),
        (
            "b.rs",
            "use std::fmt;\npub struct B;\npub fn f() { let _ = crate::a::A; let b = 1; let _ = b; }\n",
        ),
    ]);
    let arrows = krate.arrows();
    assert_eq!(arrows.len(), 1, "{arrows:?}");
    assert_eq!((arrows[0].from.as_str(), arrows[0].to.as_str()), ("b", "a"));
}

#[test]
fn an_arrow_up_a_layer_is_named() {
    let krate = synthetic(&[
        ("lib.rs", "pub mod field;\npub mod scene;\npub mod extra;\n"),
        ("field.rs", "pub fn at(_: &crate::scene::Desc) {}\n"),
        ("scene.rs", "pub struct Desc;\n"),
        (
            "extra.rs",
            "pub fn e() { crate::field::at(&crate::scene::Desc); }\n",
        ),
    ]);
    let found = layer_breaches(&krate, &[&["scene"], &["field"]]);
    assert_eq!(found.len(), 2, "{found:?}");
    assert!(
        found
            .iter()
            .all(|f| f.starts_with("extra.rs:1: room `extra`")),
        "{found:?}"
    );
    assert!(
        !found.iter().any(|f| f.starts_with("field.rs")),
        "{found:?}"
    );
    let up = layer_breaches(&krate, &[&["field"], &["scene"], &["extra"]]);
    assert_eq!(
        up,
        vec![
            "field.rs:1: field -> scene does not run down the layers of synthetic (crate::scene::Desc)"
        ]
    );
    let sideways = layer_breaches(&krate, &[&["field", "scene"], &["extra"]]);
    assert_eq!(sideways.len(), 1, "{sideways:?}");
}

#[test]
fn a_long_function_is_measured_from_fn_to_its_brace() {
    let body = "    let _ = 1;\n".repeat(MAX_FN_LINES - 1);
    let long = format!("pub fn long() {{\n{body}}}\n\nimpl S {{\n    fn fine() {{\n    }}\n}}\n");
    let exact = format!(
        "pub fn edge() {{\n{}}}\n",
        "    let _ = 1;\n".repeat(MAX_FN_LINES - 2)
    );
    let tested = format!("#[cfg(test)]\nmod tests {{\n    fn long_test() {{\n{body}    }}\n}}\n");
    let text = format!("pub struct S;\n{long}{exact}{tested}");
    let krate = synthetic(&[("lib.rs", &text)]);
    let found = long_functions(&krate);
    assert_eq!(
        found,
        vec![format!("lib.rs:2: fn long is {} lines", MAX_FN_LINES + 1)]
    );
}

#[test]
fn an_inline_module_belongs_to_its_file() {
    let krate = synthetic(&[
        ("lib.rs", "pub mod lanes;\npub mod noise;\n"),
        (
            "lanes.rs",
            "pub fn g() {}\npub fn h() { x86::f(); }\nmod x86 {\n    pub fn f() { super::g(); crate::noise::n(); }\n}\n",
        ),
        ("noise.rs", "pub fn n() {}\n"),
    ]);
    let arrows = krate.arrows();
    assert_eq!(arrows.len(), 1, "{arrows:?}");
    assert_eq!(
        (
            arrows[0].from.as_str(),
            arrows[0].to.as_str(),
            arrows[0].line
        ),
        ("lanes", "noise", 4)
    );
}
