//! Node and actor names, and voxel shards.
//!
//! Node names are fixed by role (`scheduler`, `display`, `store-I`,
//! `client-I`, as in `dray-config`); each node runs its actors under fixed
//! actor names, so every address follows from the config.

use dray_protocol::{Address, Name, VoxelId};

/// Actor name of the scheduler (on node `scheduler`).
pub const SCHEDULER: &str = "scheduler";
/// Actor name of the frame assigner (on node `scheduler`).
pub const ASSIGNER: &str = "assigner";
/// Actor name of the prefetcher (on node `scheduler`).
pub const PREFETCHER: &str = "prefetcher";
/// Actor name of a voxel store (on node `store-I`).
pub const STORE: &str = "store";
/// Actor name of a client (on node `client-I`).
pub const CLIENT: &str = "client";
/// Actor name of the display (on node `display`).
pub const DISPLAY: &str = "display";

fn addr(node: &str, actor: &str) -> Address {
    Address::parse(node, actor).expect("fixed node and actor names are valid")
}

/// Node name of store `i`.
pub fn store_node(i: usize) -> Name {
    Name::new(&format!("store-{i}")).expect("store names are valid")
}

/// Node name of client `i`.
pub fn client_node(i: usize) -> Name {
    Name::new(&format!("client-{i}")).expect("client names are valid")
}

/// The scheduler's address.
pub fn scheduler() -> Address {
    addr("scheduler", SCHEDULER)
}

/// The frame assigner's address.
pub fn assigner() -> Address {
    addr("scheduler", ASSIGNER)
}

/// The prefetcher's address.
pub fn prefetcher() -> Address {
    addr("scheduler", PREFETCHER)
}

/// The display's address.
pub fn display() -> Address {
    addr("display", DISPLAY)
}

/// Store `i`'s address.
pub fn store(i: usize) -> Address {
    Address::new(store_node(i), Name::new(STORE).expect("valid"))
}

/// Client `i`'s address.
pub fn client(i: usize) -> Address {
    Address::new(client_node(i), Name::new(CLIENT).expect("valid"))
}

/// The voxels a store serves: those whose id is `index` modulo `count`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Shard {
    /// Which residue.
    pub index: u32,
    /// Modulo what (1: every voxel).
    pub count: u32,
}

impl Shard {
    /// Every voxel.
    pub const ALL: Shard = Shard { index: 0, count: 1 };

    /// Whether this shard holds voxel `id`.
    pub fn owns(&self, id: VoxelId) -> bool {
        id % self.count == self.index
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// Where each voxel is fetched: the stores and their shards. Every voxel
/// must be owned by at least one store; among several owners a voxel goes
/// to one picked by its id, so replicas share the load.
#[derive(Clone, Debug)]
pub struct StoreRoutes {
    stores: Vec<(Shard, Address)>,
}

impl StoreRoutes {
    /// Routes over `stores`; an error names a residue no store owns.
    pub fn new(stores: Vec<(Shard, Address)>) -> Result<StoreRoutes, String> {
        if stores.is_empty() {
            return Err("no store".into());
        }
        let shards: Vec<(u32, u32)> = stores.iter().map(|(s, _)| (s.index, s.count)).collect();
        dray_config::check_shards(&shards)?;
        Ok(StoreRoutes { stores })
    }

    /// The store to ask for voxel `id` the `attempt`-th time (from 0):
    /// where several stores serve it, the ids spread over them and each
    /// new attempt asks the next one.
    pub fn store_for(&self, id: VoxelId, attempt: u32) -> &Address {
        let owners = || self.stores.iter().filter(|(s, _)| s.owns(id));
        // `new` checked that every id has an owner.
        let count = owners().count().max(1);
        let k = (id as usize / self.stores.len() + attempt as usize) % count;
        owners().nth(k).map_or(&self.stores[0].1, |(_, a)| a)
    }

    /// How many stores serve voxel `id`.
    pub fn owners(&self, id: VoxelId) -> usize {
        self.stores.iter().filter(|(s, _)| s.owns(id)).count()
    }

    /// Every store, in order.
    pub fn all(&self) -> impl Iterator<Item = &Address> {
        self.stores.iter().map(|(_, a)| a)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_route() {
        let routes = StoreRoutes::new(vec![
            (Shard { index: 0, count: 2 }, store(0)),
            (Shard { index: 1, count: 2 }, store(1)),
        ])
        .unwrap();
        assert_eq!(routes.store_for(4, 0), &store(0));
        assert_eq!(routes.store_for(7, 0), &store(1));
        // One owner: every attempt asks it.
        assert_eq!(routes.store_for(7, 3), &store(1));
        let gap = StoreRoutes::new(vec![(Shard { index: 0, count: 2 }, store(0))]);
        assert!(gap.unwrap_err().contains("1 modulo 2"));
    }
}
